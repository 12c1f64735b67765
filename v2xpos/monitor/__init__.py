"""Live view of a running master for the operator: ``MonitorState`` (what is known, sorted worst
first), ``MasterMonitor`` (fed over zenoh from what the master already publishes), the terminal
table (``table.render``) and the web page (``web.WebServer``). Command: ``v2xpos monitor``."""

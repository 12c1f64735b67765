"""Master outputs: ``can`` (frames from the DBC of ``can_dbc``: python-can + cantools), ``udp`` (binary
datagrams), ``results_csv`` (per-result rows), ``recorder`` (the MCAP session recording, its channels
and schemas in ``recording_schema``; as a child process in ``recorder_process``), ``foxglove``
(Foxglove schemas).

Import the submodule you need (``from v2xpos.output.can import CanOutput``,
``from v2xpos.output.udp import UdpOutput``); nothing is imported here so that using one output
never loads the other's dependencies. Layouts: docs/protocol.md.
"""

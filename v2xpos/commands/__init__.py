"""Command-line subcommands built on the library alone (``v2xpos.cli`` maps each name to its module
by string). A command that needs the services, the simulator or the benches lives on that floor
instead and is dispatched the same way: ``master.convoy``, ``master.service``, ``slave.service``,
``sim.demo``, ``sim.recordings``, ``bench.*``."""

"""Master outputs: ``can`` (DBC ``v2xpos.dbc`` + python-can + cantools) and ``udp`` (binary datagrams).

Import the submodule you need (``from v2xpos.output.can import CanOutput``,
``from v2xpos.output.udp import UdpOutput``); nothing is imported here so that using one output
never loads the other's dependencies. Layouts: docs/protocol.md.
"""

"""Live sessions across processes and machines through Redis (``facecast serve --redis URL``).

Without a Redis URL nothing here runs: the server is one process, in memory. With one, the process
is a *node*: it announces itself (``node``), shares the session registry with leases
(``leases``, ``records``), fans encoded frames out over pub/sub to other nodes' viewers
(``mirror``), forwards producers connected to it to the session's owner node (``inbound`` on the
owner; ``api.routes_cluster`` on the node the producer reached), and takes over the sessions of a
node that died. ``docs/CLUSTER.md`` describes the keys, channels and messages; nothing crosses
Redis as pickle: the protocol's own bytes behind a small envelope (``envelope``), and JSON models.
"""

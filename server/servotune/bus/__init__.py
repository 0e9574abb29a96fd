"""servotune on a NATS bus: rig agents, a central hub, recorded runs in one place.

``rig``: the agent a rig's own server runs (``servotune serve --bus URL --rig NAME``):
publishes its axes and answers commands through the rig's own validation, limits and
control lock. ``remote``: the hub side (``servotune hub --bus URL``): every axis of
every rig as a ``link.base.Link``/``AxisDriver`` that talks NATS, registered into
the ordinary ``Hub``, so the api and the web client work unchanged. docs/lab.md.
"""

"""A minimal fake device in one folder: the worked example of docs/architecture.md's
"Adding a device", and the test that generic code needs nothing else to list, poll and
command it (``test_fake_device.py``).

The fake servo speaks a line protocol of its own (``codec.py``) on a pseudo-terminal
(``sim.py``); ``link.py`` drives it, ``descriptor.py`` is what the UI renders, and
``entry.py`` is its registry entry (the test adds it with ``Registry.with_devices``).
"""

NAME = "fake"

"""gräbner SLAP2: RS232 ASCII with per-character echo, up to 16 modules a line."""

# The device's name: link specs (``slap2:...``), stored runs, URLs. It never changes.
NAME = "slap2"

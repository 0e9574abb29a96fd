"""CNC Designer Z1100: binary serial, one chip, three motors."""

# The device's name: link specs (``z1100:...``), stored runs, URLs. It never changes.
NAME = "z1100"

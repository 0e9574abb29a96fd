"""CNC Designer Z1100: binary serial, one chip, three motors."""

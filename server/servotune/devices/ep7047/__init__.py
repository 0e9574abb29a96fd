"""Beckhoff EP7047-1032: EtherCAT stepper terminal with positioning."""

# The device's name: link specs (``ep7047:...``), stored runs, URLs. It never changes.
NAME = "ep7047"

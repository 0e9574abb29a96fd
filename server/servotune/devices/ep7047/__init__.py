"""Beckhoff EP7047-1032: EtherCAT stepper terminal with positioning."""

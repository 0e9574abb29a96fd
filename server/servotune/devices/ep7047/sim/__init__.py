"""The simulated EP7047-1032 slave, its drive and plant."""

"""The simulated Z1100 chip and its servo loops."""

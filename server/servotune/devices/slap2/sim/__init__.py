"""The simulated SLAP2 line: firmware controller, module, line."""

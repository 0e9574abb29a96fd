"""The hub: links and axes, the one command path, fan-out, the control lock."""

"""gräbner SLAP2: RS232 ASCII with per-character echo, up to 16 modules a line."""

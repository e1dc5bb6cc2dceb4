"""The on-board unit: admission of RSU input, the OBU pipeline (clock, modes, compensation, fusion) and its node."""

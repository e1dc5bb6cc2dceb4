"""The simulated world: scenarios (each with its site), world, sensor and clock models, rendered cameras."""

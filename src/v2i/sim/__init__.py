"""The simulated world: scenarios (each with its site), world, sensor and clock models, rendered cameras."""

# the modules that declare the simulator's compiled kernels: line of sight, body states (v2i.core.jit)
KERNEL_MODULES = ("v2i.sim.occlusion", "v2i.sim.world")

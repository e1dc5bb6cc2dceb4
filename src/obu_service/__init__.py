"""The on-board unit: admission of RSU input, the OBU pipeline (clock, modes, compensation, fusion) and its node."""

# the modules that declare the compiled kernels the OBU runs (v2i.core.jit.load_kernels imports them)
KERNEL_MODULES = ("v2i.fusion.tracking", "v2i.fusion.wire", "v2i.core.frames", "v2i.fusion.geometry",
                  "v2i.fusion.lane_match", "obu_service.admission", "v2i.clock.clock_envelope", "schemas.bit_rows")

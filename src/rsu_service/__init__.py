"""The roadside unit: perception sources, the RSU pipeline (track, predict, publish) and its node."""

# the modules that declare the compiled kernels the RSU runs (v2i.core.jit.load_kernels imports them)
KERNEL_MODULES = ("v2i.fusion.tracking", "v2i.fusion.wire", "v2i.core.frames", "v2i.fusion.geometry",
                  "v2i.fusion.lane_match", "schemas.bit_rows")

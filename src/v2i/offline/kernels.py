"""The modules that declare the compiled kernels of a run, for ``v2i.core.jit.load_kernels``: every
process of a live or offline run (``RUN_KERNEL_MODULES``: the RSU's, the OBU's, the simulator's), and
with the evaluation's matching (``ALL_KERNEL_MODULES``: what ``v2i warm`` compiles ahead).
"""

import obu_service
import rsu_service
from v2i import scoring, sim

RUN_KERNEL_MODULES = tuple(dict.fromkeys((*rsu_service.KERNEL_MODULES, *obu_service.KERNEL_MODULES,
                                          *sim.KERNEL_MODULES)))
ALL_KERNEL_MODULES = RUN_KERNEL_MODULES + scoring.KERNEL_MODULES

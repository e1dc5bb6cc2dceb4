"""Value ranges and counts of the wire (shared by the per-object models and the object columns)."""

import math

from schemas import quantize as q
# m^2/s^2 (100 m/s std): no velocity measured (ObjectArray's meaning too); equals the Variance maximum
from v2i.core.objects import UNKNOWN_VELOCITY_VAR  # noqa: F401 (re-exported)

MAX_OBJECTS = 1024

# Sources of a fused object (FusedObject.sources, one byte on the wire): SOURCE_VEHICLE, the
# vehicle's own sensors; SOURCE_RSU, any cooperative source (an RSU or, later, a peer vehicle).
# Inside the OBU the tracker keeps one bit per source in an int64 (v2i.fusion.tracking.SOURCE_BITS):
# bit 0 own vehicle, bit 1 + i the OBU's RSU slot i (v2i.fusion.tracking.slot_source; slot 0 is
# SOURCE_RSU), and v2i.fusion.wire.wire_sources folds bits 1..62 into SOURCE_RSU on the way out.
SOURCE_VEHICLE = 1
SOURCE_RSU = 2

# Value ranges of the wire (|value| <= bound, or [0, bound] where negative is meaningless).
POSITION_MAX_M = 1e6
HEIGHT_MAX_M = 1e4
SIZE_MAX_M = 100.0
SPEED_MAX_MPS = 200.0
ACCEL_MAX_MPS2 = 100.0
# 30 rad/s rounded up to the grid: the quantised value of any accepted input must itself be
# accepted, or a decoded message would fail re-validation (30.0 quantises to 30.00046).
YAW_RATE_MAX = math.ceil(30.0 / q.YAW_RATE_RADPS) * q.YAW_RATE_RADPS
VARIANCE_MAX = 1e4  # m^2 or m^2/s^2; also the covariance bound
AGE_MAX_S = 1e6

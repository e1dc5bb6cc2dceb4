"""Wire quantisation steps (ETSI CPM style) and the one function that applies them.

The models quantise on construction and the codec packs the integer codes, so
``decode(encode(m)) == m`` holds exactly: both sides compute ``k * step`` with the
same ``k = round(value / step)``.
"""

import math

POSITION_M = 0.01
SIZE_M = 0.01
SPEED_MPS = 0.01
ACCEL_MPS2 = 0.01
YAW_RAD = math.radians(0.1)
YAW_RATE_RADPS = math.radians(0.1)
CONFIDENCE = 0.01
AGE_S = 0.001
COV_M2 = 0.0001


def code(value: float, step: float) -> int:
    """Integer code of ``value`` on a grid of ``step`` (round half to even)."""
    return round(value / step)


def quantize(value: float, step: float) -> float:
    """Nearest grid value: k * step with k = round(value / step)."""
    return code(value, step) * step


def wrap_angle(rad: float) -> float:
    """Wrap to [-pi, pi)."""
    return (rad + math.pi) % (2.0 * math.pi) - math.pi

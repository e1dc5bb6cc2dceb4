"""ObuPipeline._within_budget against the loop it runs when the frames exceed the budget (its previous body):
the same frames, in the same order, and the same ``rsu_objects_over_budget`` count, within and over budget."""

import numpy as np
import pytest

from v2i.core.objects import ObjectArray
from obu_service.methods import RsuFrame
from obu_service.pipeline import ObuPipeline, ObuPipelineConfig


def _within_budget_ref(pipe, frames):
    known = {s.index for s in pipe._rsus if s.known}
    kept, total = [], 0
    for frame in sorted(frames, key=lambda f: (f.rsu_index not in known, -f.valid_ns)):
        if total + len(frame.objects) > pipe.config.max_rsu_objects_per_cycle:
            pipe.rejected["rsu_objects_over_budget"] += len(frame.objects)
            continue
        total += len(frame.objects)
        kept.append(frame)
    return sorted(kept, key=lambda f: f.valid_ns) if len(kept) < len(frames) else frames


def _objects(n):
    return ObjectArray(ids=np.arange(n), cls=np.ones(n, np.int64), xy=np.zeros((n, 2)), z=np.zeros(n),
                       lwh=np.ones((n, 3)), yaw=np.zeros(n), vxy=np.zeros((n, 2)))


@pytest.mark.parametrize("budget", [0, 3, 10, 25, 1024])
def test_within_budget_keeps_what_the_loop_keeps(budget):
    rng = np.random.default_rng(budget)
    config = ObuPipelineConfig(known_rsus={"rsu-a": (0.0, 0.0), "rsu-b": (50.0, 0.0)}, max_rsu_objects_per_cycle=budget)
    new, old = ObuPipeline(config), ObuPipeline(config)
    for _ in range(200):
        frames = [RsuFrame(int(rng.integers(0, 4)), k, 0, int(rng.integers(0, 10**9)), _objects(int(rng.integers(0, 9))))
                  for k in range(int(rng.integers(0, 6)))]
        got, want = new._within_budget(frames), _within_budget_ref(old, frames)
        assert [id(f) for f in got] == [id(f) for f in want]
        assert new.rejected == old.rejected
    assert budget >= 25 or old.rejected["rsu_objects_over_budget"] > 0

"""A cascade's stage graphs, one per stage, timed in one chain as the probe times them: each exit's
graph takes the previous exit's depth map from the graph before."""

import torch

from explorer.calibration.measure import measure_network
from explorer.model import build_network, stage_specs
from explorer.space import Candidate

CASCADE = Candidate(encoder_blocks=3, width_mult=0.25, lidar_depth=2, lidar_width=8, ecu_band=1, ecu_width=16,
                    decoder_widths=(16, 8), exits=(0, 1, 2), head_depth=1, encoder_exits=(2,), lidar_exit=True,
                    exit_residual=True, exit_cascade=True)


def test_a_cascade_is_measured_stage_by_stage():
    torch.manual_seed(0)
    m = measure_network(build_network(CASCADE), (32, 48), repeats=2, warmup=1, whole=False)
    assert list(m.stage_ms) == [s.name for s in stage_specs(CASCADE)]
    assert len(m.path_ms) == CASCADE.num_paths and all(a < b for a, b in zip(m.path_ms[1:], m.path_ms[2:]))

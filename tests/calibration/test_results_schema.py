"""A probe results file edited by hand, truncated or foreign is refused in one line before the fit."""

import copy
import json
import math

import pytest

from explorer.calibration.calibrate import read_results
from explorer.calibration.results_schema import check_results
from explorer.errors import UserError

WORKLOAD = {"stage": "sweep", "layer": "pw", "kind": "pointwise", "in_shape": [8, 14, 14], "out_shape": [16, 14, 14],
            "kernel": 1, "stride": 1, "macs": 25088, "params": 128, "bytes_read": 6784, "bytes_written": 12544}
GOOD = {"format": "explorer-probe-results", "version": 1,
        "bundle": {"id": "abc", "input_size": [224, 224], "layers": [{"id": "L000", "workload": WORKLOAD}],
                   "candidates": [{"key": "k1", "candidate": {}, "input_size": [224, 224]}]},
        "device": {"onnxruntime": "1.20", "machine": "aarch64", "cpu": "Cortex-A57", "cores": 4},
        "conditions": {"provider": "CPUExecutionProvider", "threads": 4, "repeats": 15, "warmup": 3,
                       "statistic": "median"},
        "layers": {"L000": 0.3}, "stages": {"k1": {"image_encoder": 1.2}}, "energy": None}


def _edit(path, change):
    data = copy.deepcopy(GOOD)
    change(data)
    path.write_text(json.dumps(data, allow_nan=True))
    return path


EDITS = {
    "nan timing": lambda d: d["layers"].update(L000=math.nan),
    "negative timing": lambda d: d["layers"].update(L000=-1.0),
    "zero timing": lambda d: d["layers"].update(L000=0.0),
    "infinite timing": lambda d: d["layers"].update(L000=math.inf),
    "text timing": lambda d: d["layers"].update(L000="fast"),
    "negative stage": lambda d: d["stages"]["k1"].update(image_encoder=-2.0),
    "empty bundle": lambda d: d.update(bundle={}),
    "empty device": lambda d: d.update(device={}),
    "no layers in bundle": lambda d: d["bundle"].update(layers=[]),
    "bad workload": lambda d: d["bundle"]["layers"][0].update(workload={"kind": "pointwise"}),
    "threads zero": lambda d: d["conditions"].update(threads=0),
    "size text": lambda d: d["bundle"].update(input_size=["a", 3]),
}


@pytest.mark.parametrize("name", sorted(EDITS))
def test_each_hand_edit_is_one_line(tmp_path, name):
    path = _edit(tmp_path / "results.json", EDITS[name])
    with pytest.raises(UserError) as err:
        read_results(path)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_a_whole_file_passes():
    assert check_results(copy.deepcopy(GOOD), "r.json")["bundle"]["id"] == "abc"

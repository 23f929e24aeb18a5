"""Device profiles are read checked: every figure finite and in a range that prices something."""

import pytest
import yaml

from explorer.cost.devices import DeviceProfile, get_device
from explorer.errors import UserError


def _edited(tmp_path, change):
    data = get_device("tx2").to_dict()
    change(data)
    path = tmp_path / "edited.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@pytest.mark.parametrize("change, says", [
    (lambda d: d["kinds"]["conv"].update(gmacs=float("inf")), r"kinds\.conv\.gmacs must be a finite number"),
    (lambda d: d.update(bandwidth_gbs=float("nan")), "bandwidth_gbs must be a finite number"),
    (lambda d: d.update(body_exponent=1e6), r"body_exponent must lie in \[0\.5, 2\.0\]"),
    (lambda d: d.update(body_exponent=0.01), "body_exponent must lie in"),
    (lambda d: d.update(inference_overhead_ms=float("-inf")), "inference_overhead_ms must be a finite number"),
])
def test_a_profile_with_an_infinite_or_absurd_figure_is_one_line(tmp_path, change, says):
    path = _edited(tmp_path, change)
    with pytest.raises(UserError, match=says) as caught:
        DeviceProfile.from_yaml(path)
    assert "\n" not in str(caught.value)


def test_a_calibrated_body_exponent_still_reads(tmp_path):
    path = _edited(tmp_path, lambda d: d.update(body_exponent=1.125))
    assert DeviceProfile.from_yaml(path).body_exponent == 1.125

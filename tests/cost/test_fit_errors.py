"""Fit errors in one unit (relative to the figures fitted) and the words `explorer devices` uses for how
a profile's costs were obtained, for the report and the command alike."""

from explorer.cost import get_device
from explorer.cost.fit_errors import fit_errors, fit_words


def test_every_fit_is_a_relative_error_with_its_median():
    tx2, rpi4 = fit_errors(get_device("tx2")), fit_errors(get_device("rpi4"))
    assert tx2[0]["median"] == 0.1514 and tx2[0]["max"] == 0.6559          # stored relative already
    # rpi4's fit stored the largest absolute error of Table 2's losses: read from the figures it fitted
    assert rpi4[0]["count"] == 5 and rpi4[0]["median"] is not None and 0 <= rpi4[0]["median"] <= rpi4[0]["max"] < 0.01
    assert fit_words(tx2[0]) == "71 measured GPU kernels: median error 15.1%, largest 65.6% over 71 figures"
    assert fit_errors(get_device("orin-nano")) == []


def test_explorer_devices_says_published_with_a_median_for_rpi4(run_cli):
    code, out, _ = run_cli("devices")
    assert code == 0
    rows = {line.split()[0]: line for line in out.splitlines() if line.strip()}
    assert rows["tx2"].split()[1:3] == ["published", "published"] and "fit median error 15.1%" in rows["tx2"]
    assert rows["rpi4"].split()[1:3] == ["published", "published"] and "fit median error" in rows["rpi4"]

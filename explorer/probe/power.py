"""Power sensors Linux exposes (INA3221 on Jetsons, hwmon, RAPL, the Raspberry Pi 5's PMIC) and
energy per inference measured with them."""

from __future__ import annotations

import glob
import os
import re
import shutil
import subprocess
import threading
import time
from typing import Callable, Sequence

try:
    import numpy as np
except ImportError:  # the probe's main() says what to install, in one line
    np = None

# -- power sensors -------------------------------------------------------------------------------
def _read_number(path: str) -> float:
    with open(path) as f:
        return float(f.read().strip())


def _read_text(path: str, default: str = "") -> str:
    try:
        with open(path) as f:
            return f.read().strip().strip("\x00")
    except OSError:
        return default


def _is_input_rail(label: str) -> bool:
    """The board's input rail (VDD_IN on TX2/Orin, POM_5V_IN on Nano) already includes every other
    rail: summing it with them would count the SoC twice."""
    up = label.upper()
    return up == "IN" or up.endswith("_IN")


def _pick_rails(rails: list[tuple[str, object]]) -> list[tuple[str, object]]:
    inputs = [r for r in rails if _is_input_rail(r[0])]
    return inputs or rails


class PowerSensor:
    """A readable power source. ``kind`` 'power': ``read()`` is watts now; 'energy': ``read()`` is a
    counter and ``joules(a, b)`` the energy between two readings."""

    kind = "power"
    name = "sensor"
    what = ""
    interval_s = 0.02   # between samples while sampling in the background

    def read(self):  # pragma: no cover - interface
        raise NotImplementedError

    def joules(self, a, b) -> float:  # pragma: no cover - energy counters only
        raise NotImplementedError

    def describe(self) -> dict:
        return {"sensor": self.name, "kind": self.kind, "what": self.what}


class Ina3221Hwmon(PowerSensor):
    """Jetson INA3221 through hwmon: ``in{N}_input`` bus millivolts, ``curr{N}_input`` milliamperes."""

    name = "ina3221-hwmon"

    def __init__(self, channels: list[tuple[str, tuple[str, str]]]) -> None:
        self.channels = channels
        self.what = "rails " + ", ".join(label for label, _ in channels)

    def read(self) -> float:
        return sum(_read_number(v) * _read_number(c) for _, (v, c) in self.channels) / 1e6

    @classmethod
    def find(cls, root: str) -> "Ina3221Hwmon | None":
        rails = []
        for dev in sorted(glob.glob(os.path.join(root, "sys/class/hwmon/hwmon*"))):
            if _read_text(os.path.join(dev, "name")) != "ina3221":
                continue
            for volt in sorted(glob.glob(os.path.join(dev, "in[0-9]*_input"))):
                n = re.fullmatch(r"in(\d+)_input", os.path.basename(volt)).group(1)
                curr = os.path.join(dev, f"curr{n}_input")
                if os.path.isfile(curr) and _readable(volt) and _readable(curr):
                    label = _read_text(os.path.join(dev, f"in{n}_label"), f"{os.path.basename(dev)}/in{n}")
                    rails.append((label, (volt, curr)))
        return cls(_pick_rails(rails)) if rails else None


class Ina3221Iio(PowerSensor):
    """Older Jetson kernels (TX1/TX2, L4T 28-32): the ina3221x iio driver's ``in_power{N}_input``
    in milliwatts, rail names in ``rail_name_{N}``."""

    name = "ina3221-iio"

    def __init__(self, channels: list[tuple[str, str]]) -> None:
        self.channels = channels
        self.what = "rails " + ", ".join(label for label, _ in channels)

    def read(self) -> float:
        return sum(_read_number(p) for _, p in self.channels) / 1e3

    @classmethod
    def find(cls, root: str) -> "Ina3221Iio | None":
        rails, seen = [], set()
        patterns = ("sys/bus/i2c/drivers/ina3221x/*/iio:device*", "sys/bus/iio/devices/iio:device*")
        for dev in sorted(d for pat in patterns for d in glob.glob(os.path.join(root, pat))):
            real = os.path.realpath(dev)
            if real in seen:
                continue
            seen.add(real)
            for p in sorted(glob.glob(os.path.join(dev, "in_power[0-9]*_input"))):
                n = re.fullmatch(r"in_power(\d+)_input", os.path.basename(p)).group(1)
                if _readable(p):
                    rails.append((_read_text(os.path.join(dev, f"rail_name_{n}"), f"power{n}"), p))
        return cls(_pick_rails(rails)) if rails else None


class HwmonPower(PowerSensor):
    """Any other hwmon device with ``power{N}_input`` (microwatts), summed."""

    name = "hwmon-power"

    def __init__(self, files: list[tuple[str, str]]) -> None:
        self.files = files
        self.what = ", ".join(label for label, _ in files)

    def read(self) -> float:
        return sum(_read_number(p) for _, p in self.files) / 1e6

    @classmethod
    def find(cls, root: str) -> "HwmonPower | None":
        files = []
        for dev in sorted(glob.glob(os.path.join(root, "sys/class/hwmon/hwmon*"))):
            name = _read_text(os.path.join(dev, "name"), os.path.basename(dev))
            if name == "ina3221":
                continue
            for p in sorted(glob.glob(os.path.join(dev, "power[0-9]*_input"))):
                if _readable(p):
                    files.append((f"{name}/{os.path.basename(p)}", p))
        return cls(files) if files else None


class Rapl(PowerSensor):
    """Intel/AMD RAPL through powercap: top-level zones' ``energy_uj`` counters (sub-zones are
    inside them), each wrapping at its ``max_energy_range_uj``."""

    name = "rapl"
    kind = "energy"

    def __init__(self, zones: list[tuple[str, str, float]]) -> None:
        self.zones = zones
        self.what = "zones " + ", ".join(label for label, _, _ in zones)

    def read(self) -> list[float]:
        return [_read_number(p) for _, p, _ in self.zones]

    def joules(self, a: Sequence[float], b: Sequence[float]) -> float:
        total = 0.0
        for (_, _, wrap), x, y in zip(self.zones, a, b):
            d = y - x
            if d < 0:  # the counter wrapped once (a window far shorter than a wrap period)
                d += wrap
            total += d
        return total / 1e6

    @classmethod
    def find(cls, root: str) -> "Rapl | None":
        zones = []
        for z in sorted(glob.glob(os.path.join(root, "sys/class/powercap/*"))):
            base = os.path.basename(z)
            # intel-rapl:0 is a package, intel-rapl:0:0 a part of it; the mmio zone mirrors a package
            if base.count(":") != 1 or "mmio" in base:
                continue
            e, m = os.path.join(z, "energy_uj"), os.path.join(z, "max_energy_range_uj")
            if os.path.isfile(e) and _readable(e):
                wrap = _read_number(m) if os.path.isfile(m) and _readable(m) else 2.0 ** 32
                zones.append((_read_text(os.path.join(z, "name"), base), e, wrap))
        return cls(zones) if zones else None


_PMIC_LINE = re.compile(r"^\s*(\S+)_([AV])\s+(?:current|volt)\(\d+\)=\s*([-+0-9.eE]+)\s*[AV]\s*$")


def parse_pmic_adc(text: str) -> float:
    """Watts from ``vcgencmd pmic_read_adc`` (Raspberry Pi 5): every rail with both a current
    (``NAME_A current(i)=...A``) and a voltage (``NAME_V volt(j)=...V``) line, current x voltage."""
    amps, volts = {}, {}
    for line in text.splitlines():
        m = _PMIC_LINE.match(line)
        if m:
            (amps if m.group(2) == "A" else volts)[m.group(1)] = float(m.group(3))
    rails = set(amps) & set(volts)
    if not rails:
        raise ValueError("no rail with both a current and a voltage")
    return sum(amps[r] * volts[r] for r in rails)


class RpiPmic(PowerSensor):
    """Raspberry Pi 5's PMIC through ``vcgencmd pmic_read_adc`` (each reading starts the command)."""

    name = "rpi5-pmic"
    interval_s = 0.25   # every reading starts a process: sample rarely, so it does not load the CPU

    def __init__(self, command: str) -> None:
        self.command = command
        self.what = f"{command} pmic_read_adc, sum of rail current x voltage"

    def read(self) -> float:
        out = subprocess.run([self.command, "pmic_read_adc"], capture_output=True, text=True, timeout=5,
                             check=True).stdout
        return parse_pmic_adc(out)

    @classmethod
    def find(cls, command: str) -> "RpiPmic | None":
        exe = shutil.which(command)
        if exe is None:
            return None
        sensor = cls(exe)
        try:
            sensor.read()
        except (OSError, ValueError, subprocess.SubprocessError):
            return None
        return sensor


def _readable(path: str) -> bool:
    try:
        _read_number(path)
        return True
    except (OSError, ValueError):
        return False


def find_sensor(root: str = "/", vcgencmd: str = "vcgencmd") -> PowerSensor | None:
    """The first readable power source, board-level ones first (an INA3221 input rail or the Pi's
    PMIC sees the whole board; RAPL sees the CPU package only)."""
    for found in (lambda: Ina3221Hwmon.find(root), lambda: Ina3221Iio.find(root), lambda: RpiPmic.find(vcgencmd),
                  lambda: HwmonPower.find(root), lambda: Rapl.find(root)):
        sensor = found()
        if sensor is not None:
            return sensor
    return None


class PowerWindow:
    """Mean power (W) over a ``with`` block: energy counters read at both ends, instantaneous
    sensors sampled every ``interval_s`` by a background thread (and once at each end)."""

    def __init__(self, sensor: PowerSensor, interval_s: float | None = None) -> None:
        self.sensor, self.interval_s = sensor, interval_s or sensor.interval_s
        self.watts = float("nan")
        self.seconds = 0.0
        self.samples = 0

    def __enter__(self) -> "PowerWindow":
        self._stop = threading.Event()
        self._values: list[float] = []
        if self.sensor.kind == "energy":
            self._start = self.sensor.read()
        else:
            self._values.append(self.sensor.read())
            self._thread = threading.Thread(target=self._sample, daemon=True)
            self._thread.start()
        self._t0 = time.perf_counter()
        return self

    def _sample(self) -> None:
        while not self._stop.wait(self.interval_s):
            self._values.append(self.sensor.read())

    def __exit__(self, *exc) -> None:
        self.seconds = time.perf_counter() - self._t0
        if self.sensor.kind == "energy":
            self.watts = self.sensor.joules(self._start, self.sensor.read()) / max(self.seconds, 1e-9)
            self.samples = 2
        else:
            self._stop.set()
            self._thread.join()
            self._values.append(self.sensor.read())
            self.watts = float(np.mean(self._values))
            self.samples = len(self._values)


def idle_power(sensor: PowerSensor, seconds: float) -> float:
    with PowerWindow(sensor) as w:
        time.sleep(seconds)
    return w.watts


def inference_energy(sensor: PowerSensor, run: Callable[[], object], idle_w: float, min_seconds: float,
                     min_runs: int = 3) -> dict:
    """Runs ``run`` back to back for at least ``min_seconds`` while sampling power; the energy of
    one run is (mean power - idle power) x (window / runs)."""
    run()
    n = 0
    with PowerWindow(sensor) as w:
        t0 = time.perf_counter()
        while n < min_runs or time.perf_counter() - t0 < min_seconds:
            run()
            n += 1
    per_run_s = w.seconds / n
    return {"ms": per_run_s * 1000.0, "j": max(w.watts - idle_w, 0.0) * per_run_s, "watts": w.watts,
            "runs": n, "samples": w.samples}



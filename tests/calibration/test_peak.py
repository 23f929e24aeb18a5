"""The machine's peak MAC rate from its CPU description (fake /proc/cpuinfo texts and sysfs trees)."""

import pytest

from explorer.calibration.peak import host_peak

XEON = """processor\t: 0
model name\t: Intel(R) Xeon(R) Gold 6240 CPU @ 2.60GHz
cpu MHz\t\t: 1200.000
flags\t\t: fpu sse sse2 fma avx avx2 avx512f avx512_vnni
"""
PLAIN_XEON = """model name\t: Intel(R) Xeon(R) Processor
cpu MHz\t\t: 2299.998
cpu MHz\t\t: 2100.000
flags\t\t: fpu fma avx avx2
"""
PI = """processor\t: 0
BogoMIPS\t: 108.00
Features\t: fp asimd evtstrm crc32 cpuid
"""


def test_avx512_server_core_from_the_model_name_clock(tmp_path):
    p = host_peak(XEON, sysfs=tmp_path, cores=2)
    assert (p.fp32_lanes, p.fma_units, p.ghz, p.clock_source) == (16, 2, 2.6, "model name")
    assert p.fp32_gmacs == pytest.approx(2 * 2.6 * 2 * 16)      # the 166 GMAC/s
    assert p.int8_gmacs == pytest.approx(4 * p.fp32_gmacs)       # VNNI: 4 int8 MACs per fp32 lane
    assert p.fraction(83.2e6, 1.0) == pytest.approx(0.5)         # 83.2 MMAC in 1 ms = 83.2 GMAC/s


def test_cpufreq_maximum_wins_over_the_current_clock(tmp_path):
    f = tmp_path / "cpu0" / "cpufreq"
    f.mkdir(parents=True)
    (f / "cpuinfo_max_freq").write_text("3400000\n")
    p = host_peak(PLAIN_XEON, sysfs=tmp_path, cores=4)
    assert (p.ghz, p.clock_source, p.fp32_lanes, p.int8_lanes) == (3.4, "cpufreq maximum", 8, 16)


def test_highest_current_clock_and_neon_without_dot_product(tmp_path):
    assert host_peak(PLAIN_XEON, sysfs=tmp_path, cores=1).ghz == pytest.approx(2.299998)
    pi = host_peak(PI, sysfs=tmp_path, cores=4)
    assert (pi.isa, pi.fp32_lanes, pi.fma_units, pi.int8_lanes) == ("NEON", 4, 1, 8)
    assert pi.clock_source.startswith("unknown")


def test_this_machine_has_a_positive_peak():
    p = host_peak()
    assert p.cores >= 1 and p.fp32_gmacs > 0 and "GMAC/s" in p.describe()


ZEN4 = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 25
model\t\t: 17
model name\t: AMD EPYC
cpu MHz\t\t: 2596.148
flags\t\t: fpu fma avx avx2 avx512f avx512_vnni
"""


def test_zen4_takes_a_512_bit_fma_on_its_two_256_bit_units(tmp_path):
    p = host_peak(ZEN4, sysfs=tmp_path, cores=2)
    assert (p.fp32_lanes, p.fma_units) == (16, 1)
    assert p.fp32_gmacs == pytest.approx(2 * 2.596148 * 16)
    # the same flags on another vendor or family keep two full-width units
    assert host_peak(ZEN4.replace("cpu family\t: 25", "cpu family\t: 26"), sysfs=tmp_path, cores=2).fma_units == 2
    assert host_peak(ZEN4.replace("AuthenticAMD", "GenuineIntel"), sysfs=tmp_path, cores=2).fma_units == 2

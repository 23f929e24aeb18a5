"""The device probe: times a calibration bundle's ONNX graphs and samples the power sensors Linux
exposes, with nothing but Python 3, numpy and onnxruntime.

This package imports nothing else of ``explorer`` (a test enforces it): ``explorer calibrate --bundle``
ships it inside the bundle as the zip application ``probe.pyz``, and ``explorer calibrate`` runs the
same functions in-process, so a profile fitted from a probe run and one calibrated directly share one
measurement path. The runtime uses its sessions and graph rewrites too (``rewrites``).

    tar xf probe.tar && python3 probe.pyz --out results.json     # on the device
    explorer calibrate --fit results.json --out myboard.yaml     # anywhere

Results are written atomically after every graph: an interrupted probe, run again with the same
``--out``, keeps what it had measured and measures only the rest. Two fixed graphs (a convolution,
a stage) are re-timed every ``SPEED_CHECK_EVERY`` graphs; graphs timed while either shows the machine
running slow (another load, throttling) are timed again, the faster timing is kept, and the change
of speed is kept in the results.

Modules: ``formats`` (bundle manifest, results file), ``sessions`` (onnxruntime sessions, thread pool,
arena), ``rewrites`` (graph rewrites shared with the runtime), ``timing`` (timing and speed checks),
``power`` (power sensors, energy), ``identity`` (the machine), ``run`` (the probe's run and command line),
``scratch`` (scratch folders a killed process does not leave behind, SIGTERM that unwinds).
"""

from .formats import (BUNDLE_FORMAT, DEFAULT_PROVIDER, RESULTS_FORMAT, VERSION, WARMUP, BundleManifest, ProbeError,
                      load_manifest, read_results, write_atomically, write_bundle_manifest)
from .identity import device_identity
from .power import PowerSensor, PowerWindow, find_sensor, idle_power, inference_energy, parse_pmic_adc
from .rewrites import (NHWC_SUFFIX, SUFFIX, UINT8_NHWC_SUFFIX, UINT8_SUFFIX, blocked_skip_adds,
                       channels_last_skip_adds, hand_off_blocked, hand_off_channels_last, hand_off_quantized,
                       same_constant)
from .run import MEASURING_ENERGY, TIMING_AGAIN, TIMING_GRAPHS, candidate_inputs, main, run_probe, schedule
from .scratch import process_alive, remove_stale_scratch, scratch_dir, sigterm_unwinds
from .sessions import (POOL_ENV, block_size, check_provider, default_threads, session, shared_arena,
                       shared_pool_threads, thread_pool)
from .timing import (CALM_WAIT_S, REMEASURE_PASSES, SLOW, SPEED_CHECK_EVERY, SPEED_CHECK_REPEATS, SPEED_DRIFT_WARN,
                     chain_runs, chain_sessions, fixed_graph_timer, set_aside, slow_windows, slowness, speed_drift,
                     speed_layer, speed_stage, time_call, time_chain, usual_speed, wait_until_calm)

__all__ = [name for name in dir() if not name.startswith("_") and name not in {"annotations"}]

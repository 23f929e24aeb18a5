"""``explorer devices`` and ``calibrate``: device profiles, and measuring a machine to make one."""

from __future__ import annotations

from pathlib import Path

from explorer.errors import UserError
from explorer.files import check_writable_folder
from explorer.cli._common import MAX_THREADS, _add_provider, _bounded_int, _check_provider, write_output


def cmd_devices(args) -> None:
    from explorer.console import console, print_json
    from explorer.cost.devices import available_devices, get_device
    from explorer.cost.fit_errors import fit_errors, percent
    if args.name:
        p = get_device(args.name)
        if args.json:
            print_json(p.to_dict())
        else:
            console.print(p.to_yaml(), markup=False, highlight=False)
        return
    rows = []
    for name in available_devices():
        p = get_device(name)
        fits = fit_errors(p)   # relative errors, read from the checks where a fit stored absolute ones
        err = fits[0]["median"] if fits else None
        rows.append({"name": name, "calibrated": p.calibrated, "latency": p.latency_basis,
                     "energy": p.energy_basis, "precisions": ",".join(p.precisions), "description": p.description,
                     "fit_median_error": err})
    if args.json:
        print_json(rows)
        return
    console.print(f"  {'name':12s} {'latency':9s} {'energy':9s} {'precision':10s} description")
    for r in rows:
        err = f"  (fit median error {percent(r['fit_median_error'])})" if r["fit_median_error"] is not None else ""
        console.print(f"  {r['name']:12s} {r['latency']:9s} {r['energy']:9s} {r['precisions']:10s} {r['description']}{err}")
    console.print("  (measured: on the device; published: fitted to published figures; estimate: scaled from "
                  "another profile; none: not modelled)")
    console.print("  (any profile YAML file works too: --device ./mybox.yaml; make one with explorer calibrate)")


#: A profile's name names files (``explorer.cost.fit`` writes ``<name>.yaml``) and keys (an export's
#: ``expected_cost``, a report's devices): a plain name, by the rule study names follow
PLAIN_NAME = "letters, digits, '-', '_' and '.', starting with a letter or digit, at most 100 characters"
#: The file names ``--device`` reads a profile from (``explorer.cost.devices.get_device``): any other is
#: taken for a built-in profile's name, so a profile written under it could not be used
PROFILE_SUFFIXES = (".yaml", ".yml")


def _check_output(path: Path, flag: str, suffixes: tuple[str, ...], why: str, what: str, force: bool) -> None:
    """Refuses, before any work, an output ``path`` (``flag``'s) that is a folder, does not end in one of
    ``suffixes`` (``why``: what the file is), is there without --force, or lies where nothing can be written.
    The folder first: --force would not help there, the write would only fail after the work."""
    ending = ", ".join(suffixes[:-1]) + f" or {suffixes[-1]}"
    if path.is_dir():
        raise UserError(f"{path}: is a folder; give {flag} a file name ending in {ending}")
    if not path.name.endswith(suffixes):
        raise UserError(f"{flag} {path}: {why}; give a file name ending in {ending}")
    if path.exists() and not force:
        raise UserError(f"{path} exists: pass --force to overwrite it")
    check_writable_folder(path.parent, what, f"give {flag} a file in a folder you can write", keep=False)


def _profile_name(name: str | None, out: Path) -> str:
    """The profile's name (``--name``, else ``--out``'s stem), refused before any measuring where it is
    not a plain name or is a built-in profile's (one name would then stand for two profiles in an export's
    expected costs and a report's devices, and in the files a fit writes by name)."""
    from explorer.cost.devices import available_devices
    from explorer.study.storage import STUDY_NAME as PROFILE_NAME   # the one rule for a plain name
    given, name = name is not None, out.stem if name is None else name
    where = f"--name {name!r}" if given else f"--out {out.name}: the profile would be named {name!r}, which"
    if not PROFILE_NAME.fullmatch(name):
        raise UserError(f"{where} is not a plain name ({PLAIN_NAME}): give --name a plain name, e.g. --name mybox")
    builtins = available_devices()
    if name.lower() in {b.lower() for b in builtins}:   # as a case-blind file system would find it too
        raise UserError(f"{where} is a built-in device profile's name ({', '.join(builtins)}): choose another "
                        f"name, e.g. --name {name}-measured")
    return name


def _write_bundle(args) -> None:
    """``calibrate --bundle``: every mistake in the file name refused before the minute of exporting."""
    from explorer.calibration.bundle import BUNDLE_SUFFIXES, write_bundle
    from explorer.console import console, progress
    bundle = Path(args.bundle)
    _check_output(bundle, "--bundle", BUNDLE_SUFFIXES, "the bundle is a gzip-compressed tar archive (tar xf "
                  "unpacks it)", "bundle", args.force)
    with progress() as bar:
        task = bar.add_task("exporting graphs", total=None, status="")
        manifest = write_bundle(bundle, scale=0.35 if args.quick else 1.0, repeats=args.repeats,
                                progress=lambda i, n: bar.update(task, completed=i, total=n))
    console.print(f"wrote {bundle} ({bundle.stat().st_size / 1e6:.1f} MB, {len(manifest.layers)} layer "
                  f"graphs, {len(manifest.candidates)} candidates' stages, bundle {manifest.id}); on the "
                  f"device: tar xf {bundle.name} && python3 probe.pyz --out results.json")


def cmd_calibrate(args) -> None:
    from explorer.console import Phases, console, progress
    from explorer.calibration.calibrate import calibrate, fit_results, read_results
    from explorer.probe import SPEED_CHECK_EVERY, SPEED_DRIFT_WARN
    if args.bundle and args.fit:
        raise UserError("--bundle writes graphs for a device, --fit reads what the probe measured there: give one")
    _refuse_unread(args)
    if args.bundle:
        _write_bundle(args)
        return
    if not args.out:
        raise UserError("give --out PROFILE.yaml (or --bundle FILE to measure another device)")
    out = Path(args.out)
    _check_output(out, "--out", PROFILE_SUFFIXES, "a device profile is YAML, and --device reads one only from a "
                  ".yaml or .yml file", "profile", args.force)
    name = _profile_name(args.name, out)
    if args.fit:
        prof = fit_results(read_results(args.fit), name=name)
    else:
        _check_provider(args.provider)  # before the progress bar: one line, nothing else
        with progress() as bar:
            prof = calibrate(threads=args.threads, repeats=args.repeats, scale=0.35 if args.quick else 1.0,
                             name=name, provider=args.provider, energy=args.energy,
                             progress=Phases(bar),
                             log=lambda s: bar.console.print(s),
                             **(QUICK_PROBE if args.quick else {}))
    how = f"from {args.fit}" if args.fit else "on this machine"
    write_output(out, f"# Made by `explorer calibrate` {how}.\n" + prof.to_yaml())
    console.print(f"wrote {out}")
    fits = prof.provenance["fit"] + (prof.int8.provenance["fit"] if prof.int8 is not None else [])
    for fit in fits:
        console.print(f"  fit on {fit['what']}: median error {fit['median_abs_error']:.1%}, "
                      f"{fit['within_10pct']:.0%} within 10%")
    if prof.int8 is None:
        console.print("  int8: not priced (the measurements hold no int8 layer graphs)")
    cond = prof.provenance.get("conditions") or {}
    if cond.get("speed_drift") is not None:
        drift, again = cond["speed_drift"], cond.get("speed_remeasured", 0)
        console.print(f"  machine speed while measuring: varied by {drift:.0%} (fixed graphs timed every "
                      f"{SPEED_CHECK_EVERY} graphs)" + (f"; {again} graphs timed while it ran slow were timed again"
                                                        if again else "")
                      + (f"; {cond['retimed_outliers']} graphs far above the fit of the others were timed again"
                         if cond.get("retimed_outliers") else "")
                      + (f". Above {SPEED_DRIFT_WARN:.0%}: if the profile disagrees with later measurements, "
                         "calibrate again when the machine is idle" if drift > SPEED_DRIFT_WARN else ""))
    console.print(f"  energy: {prof.provenance['energy_note']}")


def _refuse_unread(args) -> None:
    """Options the chosen way of calibrating would ignore are refused, not dropped in silence: the bundle
    names its profile when it is fitted, and a fit measures nothing here."""
    if args.bundle:
        unread = [f for f, given in (("--out", args.out), ("--name", args.name)) if given is not None]
        why = "the bundle only measures; give them to --fit with what the probe measured"
    elif args.fit:
        unread = [f for f, given in (("--quick", args.quick), ("--threads", args.threads is not None),
                                     ("--provider", args.provider != "CPUExecutionProvider"),
                                     ("--no-energy", not args.energy), ("--repeats", args.repeats != REPEATS)) if given]
        why = "--fit measures nothing here; they belong to the measurement (here, or --bundle for a device)"
    else:
        return
    if unread:
        raise UserError(f"{', '.join(unread)}: not read with --{'bundle' if args.bundle else 'fit'}: {why}")


#: timings per graph (the median is kept)
REPEATS = 25

#: ``explorer calibrate --quick``: the probe times graphs again once, after a shorter wait for calm
QUICK_PROBE = {"remeasure_passes": 1, "calm_wait_s": 10.0}


def register(sub, add, reports: dict) -> None:
    """Adds this group's commands to the ``explorer`` parser."""
    s = add("devices", cmd_devices, "list device profiles, or show one with its provenance")
    s.add_argument("action", nargs="?", choices=["show"], help="show one profile")
    s.add_argument("name", nargs="?", help="profile name or file")
    s.add_argument("--json", action="store_true")

    s = add("calibrate", cmd_calibrate, "measure this machine with onnxruntime and write a device profile; "
            "or pack the measurement for another device (--bundle) and fit what it measured (--fit)")
    s.add_argument("--out", help="profile YAML file to write, .yaml or .yml (needed unless --bundle)")
    s.add_argument("--bundle", metavar="FILE.tar", help="write the graphs and probe.pyz (needs only python3, numpy "
                   "and onnxruntime) for a device, instead of measuring here: a gzip-compressed tar (.tar, .tar.gz "
                   "or .tgz)")
    s.add_argument("--fit", metavar="RESULTS.json", help="fit --out to what probe.pyz measured on a device")
    s.add_argument("--name", help="profile name (default: the file's stem): letters, digits, '-', '_' and '.', "
                   "not a built-in profile's")
    s.add_argument("--threads", type=_bounded_int(1, MAX_THREADS, "threads"), default=None)
    s.add_argument("--repeats", type=int, default=REPEATS)
    _add_provider(s)
    s.add_argument("--no-energy", dest="energy", action="store_false", help="do not sample power sensors")
    s.add_argument("--quick", action="store_true", help="a third of the sweep, and graphs timed while the machine "
                   "ran slow timed again once, after waiting up to 10 s (for a first look)")
    s.add_argument("--force", action="store_true", help="overwrite --out or --bundle")

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


def cmd_calibrate(args) -> None:
    from explorer.console import Phases, console, progress
    from explorer.calibration.calibrate import calibrate, fit_results, read_results
    from explorer.probe import SPEED_CHECK_EVERY, SPEED_DRIFT_WARN
    if args.bundle and args.fit:
        raise UserError("--bundle writes graphs for a device, --fit reads what the probe measured there: give one")
    if args.bundle:
        from explorer.calibration.bundle import write_bundle
        bundle = Path(args.bundle)
        if bundle.exists() and not args.force:
            raise UserError(f"{bundle} exists: pass --force to overwrite it")
        check_writable_folder(bundle.parent, "bundle", "give --bundle a file in a folder you can write", keep=False)
        with progress() as bar:
            task = bar.add_task("exporting graphs", total=None, status="")
            manifest = write_bundle(bundle, scale=0.35 if args.quick else 1.0, repeats=args.repeats,
                                    progress=lambda i, n: bar.update(task, completed=i, total=n))
        console.print(f"wrote {bundle} ({bundle.stat().st_size / 1e6:.1f} MB, {len(manifest.layers)} layer "
                      f"graphs, {len(manifest.candidates)} candidates' stages, bundle {manifest.id}); on the "
                      f"device: tar xf {bundle.name} && python3 probe.pyz --out results.json")
        return
    if not args.out:
        raise UserError("give --out PROFILE.yaml (or --bundle FILE to measure another device)")
    out = Path(args.out)
    if out.exists() and not args.force:
        raise UserError(f"{out} exists: pass --force to overwrite it")
    if out.is_dir():
        raise UserError(f"{out}: is a folder; give --out a file name")
    check_writable_folder(out.parent, "profile", "give --out a file in a folder you can write", keep=False)
    if args.fit:
        prof = fit_results(read_results(args.fit), name=args.name or out.stem)
    else:
        _check_provider(args.provider)  # before the progress bar: one line, nothing else
        with progress() as bar:
            prof = calibrate(threads=args.threads, repeats=args.repeats, scale=0.35 if args.quick else 1.0,
                             name=args.name or out.stem, provider=args.provider, energy=args.energy,
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
    s.add_argument("--out", help="profile YAML file to write (needed unless --bundle)")
    s.add_argument("--bundle", metavar="FILE.tar", help="write the graphs and probe.pyz (needs only python3, numpy "
                   "and onnxruntime) for a device, instead of measuring here")
    s.add_argument("--fit", metavar="RESULTS.json", help="fit --out to what probe.pyz measured on a device")
    s.add_argument("--name", help="profile name (default: the file's stem)")
    s.add_argument("--threads", type=_bounded_int(1, MAX_THREADS, "threads"), default=None)
    s.add_argument("--repeats", type=int, default=25)
    _add_provider(s)
    s.add_argument("--no-energy", dest="energy", action="store_false", help="do not sample power sensors")
    s.add_argument("--quick", action="store_true", help="a third of the sweep, and graphs timed while the machine "
                   "ran slow timed again once, after waiting up to 10 s (for a first look)")
    s.add_argument("--force", action="store_true", help="overwrite --out or --bundle")

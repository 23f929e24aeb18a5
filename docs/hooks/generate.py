"""MkDocs hook: the pages that are generated at build time, so that they never drift.

- ``cli.md``: one section per command and subcommand of ``explorer``, read off the argparse parser
  that the command line itself uses (``explorer.cli.build_parser``).
- ``benchmarks.md``: the latest record of each benchmark and experiment under ``benchmarks/results/``,
  which the suites (``benchmarks/``) and the experiments (``experiments/``) write (schema 1, below). The records shown are also copied into the site, so
  the page can link to them.

Each page holds a placeholder comment that the hook replaces; the functions that build the Markdown
(``cli_markdown``, ``benchmarks_markdown``) take plain arguments so that tests can call them.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import re
import sys
from pathlib import Path

log = logging.getLogger("mkdocs.hooks.generate")

CLI_PLACEHOLDER = "<!-- generated: cli-reference -->"
BENCHMARKS_PLACEHOLDER = "<!-- generated: benchmark-records -->"
RESULTS = Path("benchmarks") / "results"          # relative to the repository root
#: <UTC timestamp>-<short commit>.json; the timestamp sorts in time order as text
RECORD_NAME = re.compile(r"^(\d{8}T\d{6}Z)-([0-9A-Za-z]+)\.json$")
HELP_COLUMNS = "88"      # argparse wraps help to the terminal; fix it so the page is the same everywhere
ANSI = re.compile(r"\x1b\[[0-9;]*m")

# Records found by on_files, shown by on_page_markdown: {benchmark: (path, record)}, problems.
_records: dict[str, tuple[Path, dict]] = {}
_problems: list[str] = []


# -- MkDocs entry points --------------------------------------------------------------------------
def on_files(files, config):
    """Finds the latest record of each benchmark and adds it to the site (the page links to it)."""
    from mkdocs.structure.files import File
    root = _root(config)
    found, problems = latest_records(root / RESULTS)
    _records.clear()
    _records.update(found)
    _problems[:] = problems
    for problem in problems:
        log.warning("benchmark record %s", problem)
    for path, _ in found.values():
        src_uri = path.relative_to(root).as_posix()
        if files.get_file_from_path(src_uri) is None:
            files.append(File.generated(config, src_uri, abs_src_path=str(path)))
    return files


#: ``{{ figure: BENCHMARK/FIGURE }}`` in any page: that figure's median in the benchmark's latest record
FIGURE = re.compile(r"\{\{\s*figure:\s*(\w+)/(\w+)\s*\}\}")


def figure_text(records: dict[str, tuple[Path, dict]], benchmark: str, name: str) -> str | None:
    """A figure's median with its unit (and its range over the repetitions), or None if no record has it."""
    rec = records.get(benchmark, (None, None))[1]
    fig = next((f for f in (rec or {}).get("figures", []) if f["name"] == name), None)
    if fig is None:
        return None
    unit = "x" if fig["unit"] == "x" else f" {fig['unit']}" if fig["unit"] else ""
    # "to", not a dash: a range of signed figures (a lead, a difference) reads "-0.1 to 0.05"
    spread = f" ({_num(fig['min'])} to {_num(fig['max'])}, {len(fig['reps'])} reps)" if len(fig["reps"]) > 1 else ""
    return f"{_num(fig['median'])}{unit}{spread}"


def _figures(markdown: str, src: str) -> str:
    """Replaces every figure reference by the latest record's value; a figure no record holds is a
    build warning (so ``mkdocs build --strict`` fails rather than print a stale or made-up number)."""
    def one(m: re.Match) -> str:
        text = figure_text(_records, m.group(1), m.group(2))
        if text is None:
            log.warning("%s: no benchmark record holds figure %s/%s", src, m.group(1), m.group(2))
            return "(not measured)"
        return text
    return FIGURE.sub(one, markdown)


def on_page_markdown(markdown, page, config, files):
    """Fills the placeholders of cli.md and benchmarks.md, and figure references in every page."""
    src = page.file.src_uri
    markdown = _figures(markdown, src)
    if src == "cli.md":
        return _fill(markdown, CLI_PLACEHOLDER, src, lambda: cli_markdown(_parser(config)))
    if src == "benchmarks.md":
        root = _root(config)
        return _fill(markdown, BENCHMARKS_PLACEHOLDER, src,
                     lambda: benchmarks_markdown(_records, root, _problems))
    return markdown


#: a Sphinx cross-reference role as it reaches the HTML from a docstring or a record (``:func:`name```)
ROLE = re.compile(r":(?:py:)?(?:func|class|meth|mod|attr|data|exc|obj|const):<code>(~?)([^<]*)</code>")


def on_page_content(html, page, config, files):
    """The package's docstrings use Sphinx roles, which mkdocstrings leaves as text: each becomes the
    code it names (``~a.b.C`` as ``C``, as Sphinx shows it)."""
    return ROLE.sub(lambda m: f"<code>{m.group(2).rsplit('.', 1)[-1] if m.group(1) else m.group(2)}</code>", html)


def _fill(markdown: str, placeholder: str, src: str, make) -> str:
    if placeholder not in markdown:
        log.warning("%s: placeholder %s is missing, nothing generated", src, placeholder)
        return markdown
    return markdown.replace(placeholder, make())


def _root(config) -> Path:
    """The repository root: where mkdocs.yml is."""
    return Path(config["config_file_path"]).resolve().parent


def _parser(config) -> argparse.ArgumentParser:
    root = str(_root(config))
    if root not in sys.path:      # a checkout that is not installed still documents itself
        sys.path.insert(0, root)
    from explorer.cli import build_parser
    return build_parser()


# -- CLI reference --------------------------------------------------------------------------------
def cli_markdown(parser: argparse.ArgumentParser) -> str:
    """The parser's help, then one section per subcommand (any depth), each with its usage and help
    as the command prints them."""
    saved = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = HELP_COLUMNS
    try:
        out: list[str] = []
        _cli_section(parser, None, 2, out, top=True)
        return "\n".join(out)
    finally:
        if saved is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = saved


def subcommands(parser: argparse.ArgumentParser) -> list[tuple[str, str | None, argparse.ArgumentParser]]:
    """(name, one-line help, parser) of each subcommand of ``parser``, in the order it lists them;
    aliases are left out (they share their command's parser)."""
    out, seen = [], set()
    for action in parser._actions:
        if not isinstance(action, argparse._SubParsersAction):
            continue
        helps = {a.dest: a.help for a in action._choices_actions}
        for name, sub in action.choices.items():
            if id(sub) in seen:
                continue
            seen.add(id(sub))
            out.append((name, helps.get(name), sub))
    return out


def _cli_section(parser: argparse.ArgumentParser, help_: str | None, level: int, out: list[str],
                 top: bool = False) -> None:
    if not top:
        out.append(f"{'#' * min(level, 6)} {parser.prog}\n")
        if help_ and help_ != argparse.SUPPRESS and not parser.description:
            out.append(f"{_sentence(help_)}\n")   # the help is said again only when usage would not say it
    text = ANSI.sub("", parser.format_help()).rstrip()
    out.append(f"```text\n{text}\n```\n")
    for name, sub_help, sub in subcommands(parser):
        _cli_section(sub, sub_help, level if top else level + 1, out)


def _sentence(text: str) -> str:
    text = " ".join(text.split())
    return text[:1].upper() + text[1:] + ("" if text.endswith(".") else ".")


# -- benchmark records ----------------------------------------------------------------------------
MACHINE_KEYS = ("cpu_model", "cpu_flags", "cores", "peak_gmacs_fp32", "platform", "python", "torch", "onnxruntime")
FIGURE_KEYS = ("name", "label", "unit", "reps", "median", "min", "max", "better")
RECORD_KEYS = ("schema", "benchmark", "title", "description", "command", "commit", "dirty", "date", "machine",
               "figures", "notes")


def check_record(record) -> str | None:
    """What is wrong with a record (schema 1), or None."""
    if not isinstance(record, dict):
        return "is not a JSON object"
    if record.get("schema") != 1:
        return f"has schema {record.get('schema')!r}, this page reads schema 1"
    missing = [k for k in RECORD_KEYS if k not in record]
    if missing:
        return f"lacks {', '.join(missing)}"
    machine = record["machine"]
    if not isinstance(machine, dict) or any(k not in machine for k in MACHINE_KEYS):
        return f"machine must hold {', '.join(MACHINE_KEYS)}"
    figures = record["figures"]
    if not isinstance(figures, list):
        return "figures must be a list"
    for i, fig in enumerate(figures):
        if not isinstance(fig, dict) or any(k not in fig for k in FIGURE_KEYS):
            return f"figure {i} must hold {', '.join(FIGURE_KEYS)}"
        numbers = [fig["median"], fig["min"], fig["max"], *fig["reps"]] if isinstance(fig["reps"], list) else None
        if numbers is None or not all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in numbers):
            return f"figure {fig['name']!r}: reps, median, min and max must be numbers"
        if fig["better"] not in ("lower", "higher", None):
            return f"figure {fig['name']!r}: better must be lower, higher or null"
    return None


def latest_records(results: Path) -> tuple[dict[str, tuple[Path, dict]], list[str]]:
    """{benchmark: (path, record)} of the newest valid record in each ``results/<benchmark>/``, and
    one line per file that could not be used. Newest = the latest timestamp in the file name."""
    found: dict[str, tuple[Path, dict]] = {}
    problems: list[str] = []
    if not results.is_dir():
        return found, problems
    for folder in sorted(p for p in results.iterdir() if p.is_dir()):
        named = sorted((m.group(1), p) for p in folder.glob("*.json") if (m := RECORD_NAME.match(p.name)))
        for _, path in reversed(named):           # newest first; an unusable one gives way to the one before
            try:
                record = json.loads(path.read_text())
            except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
                problems.append(f"{path}: unreadable ({exc})")
                continue
            wrong = check_record(record)
            if wrong is None and record["benchmark"] != folder.name:
                wrong = f"names benchmark {record['benchmark']!r} but lies in {folder.name}/"
            if wrong:
                problems.append(f"{path}: {wrong}")
                continue
            found[folder.name] = (path, record)
            break
    return found, problems


def benchmarks_markdown(records: dict[str, tuple[Path, dict]], root: Path, problems: list[str] = ()) -> str:
    """One section per benchmark (sorted by name): title, description, its figures, and where and how
    they were measured."""
    if not records:
        text = ("No benchmark records yet. Run a benchmark, for example `python -m benchmarks.runtime --only path0`: "
                "it writes its record to `benchmarks/results/<benchmark>/<UTC time>-<commit>.json`, and the next "
                "build of this site shows the latest record of each benchmark here.\n")
    else:
        text = _summary(records) + "\n".join(_benchmark_section(name, path, rec, root)
                                            for name, (path, rec) in sorted(records.items()))
    if problems:
        text += "\n!!! warning \"Records left out\"\n\n" + "".join(f"    - `{p}`\n" for p in problems)
    return text


#: what a user asks first, each answered by one figure of one benchmark's latest record
SUMMARY = (
    ("How long `make search` takes from a fresh clone, setup included (the record says how busy the machine was)",
     "bench_make_search_load", "wall_s", 1 / 60, "min"),
    ("...its summary's answer: the retrained winner's anytime loss over the retrained paper design's",
     "bench_make_search_load", "winner_over_paper", 1, "x"),
    ("Candidates the search estimates a minute (2-core CPU)", "bench_search_rate", "candidates_per_minute", 1, ""),
    ("Peak memory of `make search`'s job (resident, its process tree)", "bench_search_memory", "peak_rss_gb", 1, "GB"),
    ("How well the estimate ranks the space (Kendall tau against long stand-alone trainings)", "bench_fidelity",
     "tau_supernet", 1, ""),
    ("...and the long trainings' own seed-to-seed tau, the ceiling", "bench_fidelity", "labels_seed_tau", 1, ""),
    ("How the ranking at the search's 64x64 carries to 224x224 (Kendall tau)", "bench_resolution",
     "tau_small_to_deploy", 1, ""),
    ("The paper design at 224x224 with the study's recipe (anytime loss, m)", "bench_resolution",
     "anytime_tuned", 1, ""),
    ("...trained at 64x64 only, run at 224x224", "bench_resolution", "anytime_small", 1, ""),
    ("The search's winner at `make search`'s length over the paper design (anytime loss, both retrained "
     "600 steps)", "bench_sampler_value", "ratio_default", 1, "x"),
    ("...over the envelope of dedicated networks, retrained the same way", "bench_sampler_value",
     "envelope_ratio_default", 1, "x"),
    ("Supernet training step: 2 CPU threads of the GPU machine over its GPU", "bench_gpu", "gpu_speedup_default", 1,
     "x"),
    ("A whole study at 224x224 on one GPU, `--time-limit 4m` (one study)", "bench_gpu_study", "study_s", 1 / 60,
     "min"),
    ("...its winner's anytime loss over the paper design's, both retrained at 224x224", "bench_gpu_study",
     "winner_ratio", 1, "x"),
)


def _summary(records: dict[str, tuple[Path, dict]]) -> str:
    """The page's opening table: the figures a user cares about, each from its record (left out where no
    record holds it)."""
    rows = []
    for question, bench, name, scale, unit in SUMMARY:
        figure = next((f for f in records.get(bench, (None, {"figures": []}))[1]["figures"] if f["name"] == name),
                      None)
        if figure is None:
            continue
        spread = f"{_num(figure['min'] * scale)} – {_num(figure['max'] * scale)}"
        rows.append(f"| {question} | **{_num(figure['median'] * scale)}** {unit} | {spread} | "
                    f"[{bench}](#{bench}) |")
    if not rows:
        return ""
    return ("## At a glance {#at-a-glance}\n\nMedians of the latest records (min – max over their repetitions); "
            "each links to its benchmark below.\n\n| question | median | min – max | record |\n|---|---:|---:|---|\n"
            + "\n".join(rows) + "\n\n")


def _benchmark_section(name: str, path: Path, rec: dict, root: Path) -> str:
    try:
        rel = path.resolve().relative_to(root).as_posix()
    except ValueError:            # a results folder outside the repository (tests)
        rel = path.as_posix()
    m = rec["machine"]
    peak = m["peak_gmacs_fp32"]
    machine = f"{m['cpu_model']}, {m['cores']} cores" + (f", peak {_num(peak)} GMAC/s fp32" if peak else "") + \
        (f"; GPU {m['gpu']}" if m.get("gpu") else "")
    commit = f"`{rec['commit']}`" + (" (with uncommitted changes)" if rec["dirty"] else "")
    # the benchmark's name is the heading's anchor: the guides and the evidence page link to benchmarks.md#NAME
    lines = [f"## {rec['title']} {{#{name}}}\n", f"`{name}`: {rec['description']}\n"]
    if rec["figures"]:
        lines.append("| figure | median | min – max | reps | unit |")
        lines.append("|---|---:|---:|---:|---|")
        for f in rec["figures"]:
            better = {"lower": " (lower is better)", "higher": " (higher is better)"}.get(f["better"], "")
            lines.append(f"| {_cell(f['label'])}{better} | {_num(f['median'])} | {_num(f['min'])} – {_num(f['max'])} "
                         f"| {len(f['reps'])} | {_cell(f['unit'])} |")
        lines.append("")
    else:
        lines.append("The record holds no figures.\n")
    if rec["notes"]:
        lines.append(f"{rec['notes']}\n")
    lines.append(f"Measured on {machine} ({m['platform']}; Python {m['python']}, torch {m['torch']}, "
                 f"onnxruntime {m['onnxruntime']}), commit {commit}, {rec['date']}, with `{rec['command']}`. "
                 f"Record: [`{rel}`]({rel}).\n")   # on_files copies it into the site at the same path
    return "\n".join(lines)


def _num(x) -> str:
    return f"{x:.4g}" if isinstance(x, float) else str(x)


def _cell(text) -> str:
    return str(text).replace("|", "\\|").replace("\n", " ")

"""Check that a preset's committed tables regenerate from its committed run archive alone.

Each paper table (and its val copy) runs as `python -m bench +experiment=NAME preset=P`, and each study
table of conf/study as `+study=NAME` (named `studies/NAME`, on the split it scores), with the seeds its
committed caption names, into an empty run store with no rendered data and its results in a scratch
folder, reading `results/P/runs`. A table whose every run is archived and current is written from the
archive in seconds; one that would render or train (a stale run, weights a Cascade needs, frames rendered
again since it was scored, a config that no longer names the recorded runs) is stopped at the first sign
of it (the data step's "rendering what is missing") and named with the table's reason. A table written
is compared with the committed one, column by column.

    .venv/bin/python scripts/regenerates_from_archive.py                     # the cpu tables, test and val
    .venv/bin/python scripts/regenerates_from_archive.py --tables sota ipt --splits test
    .venv/bin/python scripts/regenerates_from_archive.py --tables studies/dark_bias
    SRD_VGG16_WEIGHTS=/path/to/vgg16.pth .venv/bin/python scripts/regenerates_from_archive.py --tables perceptual

Exit status 0 when every table checked regenerates and matches, 1 otherwise. About 15 s a table on 2 cores.
"""
from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

import pandas as pd
from omegaconf import OmegaConf

REPO = Path(__file__).resolve().parents[1]
STUDIES = "studies/"   # a study's table folder, under results/<preset>/


def conf_file(name: str) -> Path:
    """An experiment's config, or a study's (`studies/NAME`)."""
    if name.startswith(STUDIES):
        return REPO / "conf" / "study" / f"{name.removeprefix(STUDIES)}.yaml"
    return REPO / "conf" / "experiment" / f"{name}.yaml"


def kind(name: str) -> str:
    """An experiment's kind, from its file or the experiment its defaults start from."""
    conf = OmegaConf.load(conf_file(name))
    found = OmegaConf.select(conf, "experiment.kind")
    return found if found is not None else kind(conf.defaults[0].removeprefix("/experiment/"))


def committed_tables(preset: str) -> list[str]:
    """The paper tables `+experiment=all` runs and the studies of conf/study, of kind table (not the MAC
    audit, stability, timing or verdicts, which measure this machine, compute cases or read other tables),
    that the preset has a committed table.csv of."""
    listed = OmegaConf.load(REPO / "conf" / "experiment" / "all.yaml").experiment.tables
    studies = [STUDIES + path.stem for path in sorted((REPO / "conf" / "study").glob("*.yaml"))]
    return [name for name in [*listed, *studies]
            if kind(name) == "table" and (REPO / "results" / preset / name / "table.csv").is_file()]


def differences(committed: Path, regenerated: Path) -> list[str]:
    """What differs between two tables' folders: the caption (table.md's first line), the rows, and each
    column of table.csv added, removed or with other values."""
    caption = [] if _caption(committed) == _caption(regenerated) else ["the caption"]
    old, new = pd.read_csv(committed / "table.csv"), pd.read_csv(regenerated / "table.csv")
    changed = caption + sorted(set(old.columns) ^ set(new.columns))
    if len(old) != len(new):
        return changed + ["the rows"]
    return changed + [c for c in old.columns if c in new.columns and not old[c].equals(new[c])]


def _caption(folder: Path) -> str:
    return (folder / "table.md").read_text().split("\n", 1)[0]


def recorded_seeds(committed: Path) -> list[str]:
    """`seeds=[...]` as the committed table's caption names them: a table run with other seeds than its
    config's (a study run on seed 0 only, as docs/studies.md says) is checked as it was run."""
    found = re.search(r"seeds (\[[\d, ]+\])", _caption(committed))
    return [f"seeds={found.group(1).replace(' ', '')}"] if found else []


def regenerate(name: str, preset: str, split: str, work: Path, extra: list[str]) -> tuple[str, Path | None]:
    """(verdict, the regenerated table's folder or None): run the table, stopping it where it would render."""
    # the log lines of any render (and so of any training), and of why a table renders; imported here, not at
    # the top: bench imports torch, which --help need not wait for
    from bench.experiments.datasets import RENDERING
    from bench.experiments.table import RENDERING_BECAUSE
    where = work / f"{name.replace('/', '-')}-{split}"
    choice = f"+study={name.removeprefix(STUDIES)}" if name.startswith(STUDIES) else f"+experiment={name}"
    command = [sys.executable, "-m", "bench", choice, f"preset={preset}",
               f"runs_dir={work / 'runs'}", f"data_dir={where / 'data'}", f"results_dir={where / 'results'}",
               f"runs_archive={REPO / 'results' / preset / 'runs'}", "tracking=none", "progress=false",
               *([] if split == "test" or name.startswith(STUDIES) else [f"eval.split={split}"]), *extra]
    log = where / "log.txt"
    where.mkdir(parents=True, exist_ok=True)
    with open(log, "w") as out:
        # SIGINT's default disposition in the child: where this script runs in the background of a
        # non-interactive shell, SIGINT is ignored, and the command would render on instead of stopping
        # (and stopping its render workers) as Ctrl-C in a terminal does. Its own process group: a table that
        # does not stop, or this script stopped, takes its render workers with it (killpg)
        proc = subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
                                start_new_session=True)
        why = ""
        try:
            for line in proc.stdout:
                out.write(line)
                if RENDERING_BECAUSE in line:  # bench.experiments.table.render_what_runs says why
                    why = line.split(RENDERING_BECAUSE, 1)[1].strip()
                if RENDERING in line:
                    proc.send_signal(signal.SIGINT)
                    try:
                        out.write(proc.communicate(timeout=120)[0])
                    except subprocess.TimeoutExpired:  # it did not stop on SIGINT
                        _kill_group(proc)
                        out.write(proc.communicate(timeout=30)[0])
                    shown = why if len(why) <= 400 else why[:400] + " ..."
                    return f"would render or train ({shown or 'see the log'}; log: {log})", None
            proc.wait()
        except BaseException:  # Ctrl-C or an error here: nothing of the table outlives this script
            _kill_group(proc)
            raise
    if proc.returncode != 0:
        return f"exit {proc.returncode} (log: {log})", None
    return "regenerated", where / "results" / ("" if split == "test" else split) / name


def _kill_group(proc: subprocess.Popen) -> None:
    try:
        os.killpg(proc.pid, signal.SIGKILL)
    except ProcessLookupError:  # gone already
        pass


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--preset", default="cpu")
    parser.add_argument("--tables", nargs="*", help="default: every paper table of +experiment=all and every study "
                                                    "of kind table committed for the preset (studies/NAME)")
    parser.add_argument("--splits", nargs="*", default=["test", "val"],
                        help="test: results/<preset>/<table>; another: results/<preset>/<split>/<table>, where "
                             "committed. A study is checked with test, on the split it scores "
                             "(results/<preset>/studies/<name>)")
    parser.add_argument("--work", type=Path, help="scratch folder (default: a new one under the system's tmp)")
    parser.add_argument("overrides", nargs="*", help="more overrides for every table, e.g. vgg.weights=...")
    args = parser.parse_args(argv)
    work = args.work or Path(tempfile.mkdtemp(prefix="regenerates-"))
    failed = 0
    for name in args.tables or committed_tables(args.preset):
        for split in [s for s in args.splits if s == "test"] if name.startswith(STUDIES) else args.splits:
            committed = REPO / "results" / args.preset / ("" if split == "test" else split) / name
            if not (committed / "table.csv").is_file():
                continue
            verdict, table = regenerate(name, args.preset, split, work, recorded_seeds(committed) + args.overrides)
            if table is not None:
                differs = differences(committed, table)
                verdict = f"differs from the committed table in {', '.join(differs)}" if differs else "matches"
            failed += verdict != "matches"
            print(f"{name} ({'its own split' if name.startswith(STUDIES) else split}): {verdict}", flush=True)
    print(f"{failed} table(s) do not regenerate as committed; scratch folder {work}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())

"""OccLE's ablations (Tab. 3, Tab. 4(a)(b), Tab. C.2) on the synthetic world, as mean ± std over seeds.

Each row is one shipped config (``occle/<row>``) trained per seed in its own ``occplug fit`` process on the same
budget and evaluated on the validation split (camera mask): mIoU and IoU of the final phase, plus mIoU of the
semantic branch's ``S`` (Phase I) for Tab. 3 and IoU of the geometric branch's ``G`` for Tab. 4(a)::

    python -m occplug_occle.tools.ablate                                  # 3 seeds, every row, default world
    python -m occplug_occle.tools.ablate --rows three_phase_10pct baseline_10pct full_100pct   # the pass/fail rows
    python -m occplug_occle.tools.ablate --dry-run                        # the planned runs and optimizer steps
    python -m occplug_occle.tools.ablate --seeds 0 --preset tiny --epochs 0.02 --rows three_phase_10pct baseline_10pct

With ``--results DIR`` it writes one JSON per row and seed (``DIR/<row>-seed<N>.json``: the row's values, the
budget, that run's own ``occplug fit`` overrides, the ablation's command line and the code's commit), the
files the claims tables script (``claims_tables.py``) reads.

Pass/fail (printed when the rows ran): OccLE at 10 % labels (``three_phase_10pct``) beats the stated baseline at
10 % (``baseline_10pct``: Tab. 4(b)'s "Baseline", OccLE with its semantic branch, geometric branch and projection
supervision off, trained on the labelled 10 %), and reaches >= 75 % of its own full-label mIoU (``full_100pct``).
The other rows (teacher vs student geometry, the pipeline ablations) are reported, not judged.

Budget. ``--epochs`` scales every phase's ``max_epochs`` (at least 1); validation runs once, at the end of each
phase (``trainer.check_val_every_n_epoch`` past the last epoch). Every row trains every one of its phases in its
own run (a table is then one command, each seed's run whole). ``--reuse-phases`` instead copies the phases a row
shares with the ``three_phase_10pct`` run of the same seed (the same phase config, freeze, init_from and pseudo
labels, in the same order from the first phase) from that run: ``geometry_teacher`` and ``geometry_student`` then
train nothing, ``no_projection``, ``no_voxel_labels``, ``teacher_in_fusion`` and ``no_geometric`` only Phase III.
That is cheaper and pairs the rows phase by phase; with the same code and thread count a copy should equal what
the row would train itself (a phase's run is bit-reproducible on CPU for a seed, code and thread count, tested in
``test_occle_reproducibility.py``; a row against the donor was not compared), but a copy made at other code is not
(``results/occle/reproducibility``). ``--dry-run`` prints the optimizer steps each row trains.

CPU budget (OMP_NUM_THREADS=1, one core of a 2-core machine running two rows side by side; measured on the
``default`` world, batch 2, the recipes' 32 x 32 x 8 grid): a step takes ~0.9 s in Phase I, ~0.7 s in Phase II
(teacher, student), ~2.5 s in Phase III and the baseline (the Dual Mamba's backward dominates), and every phase
adds ~10-30 s of start-up and validation. ``--epochs 0.3`` (the README's table: 1,044 / 864 / 180 steps for
``three_phase_10pct`` / ``full_100pct`` / ``baseline_10pct``) took ~35 / ~32 / ~8 min per seed, 1 h 35 min for
those three rows and 3 seeds on 2 cores. ``--epochs 1`` trains 3,480 / 2,880 / 600 steps (~2.7 CPU hours per seed
for the three rows); every row at ``--epochs 1`` is 16,800 steps per seed. Every phase keeps >= 1 epoch. The smoke
run ``--seeds 0 --preset tiny --epochs 0.02 --rows three_phase_10pct baseline_10pct`` took 90 s.

``--set`` items go to every run; one under ``phases.<name>.`` only to the rows that declare that phase (e.g.
``--set phases.fusion.trainer.max_epochs=6`` lengthens Phase III of the OccLE rows, not the baseline).

``--until PHASE`` trains each row only up to and including PHASE, in ``<row>-seed<N>-until-<PHASE>``; a whole run
of the row that finished already answers for it. ``--until semantic --rows three_phase_10pct primary_only`` is
Tab. 3 (mIoU of ``S``) at Phase I's cost; the pipeline's columns are then left empty.

``--val-scenes N`` evaluates on N validation scenes (the ``default`` world holds 4 x 6 frames; more lowers the
spread between seeds). Results go to ``--out`` (default ``runs/occle_ablate``): one run directory per row and
seed, and ``table.json`` (``table-until-<phase>.json`` with ``--until``). A finished run directory is reused,
so an interrupted ablation continues where it stopped.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import statistics
import sys
import time
from pathlib import Path
from typing import Any

from occplug.run.bench import code_commit, evaluate_in_process, fit_in_process, mean_std, write_seed_result

#: Row name (the config ``occle/<name>``) -> its label in the tables.
ROWS = {
    "three_phase_10pct": "OccLE, 10 % labels (Sem. + Geo. + Proj.)",
    "full_100pct": "OccLE, 100 % labels",
    "baseline_10pct": "Baseline, 10 % (no Sem., Geo., Proj.)",
    "no_semantic": "OccLE 10 %, w/o Sem.",
    "no_geometric": "OccLE 10 %, w/o Geo.",
    "no_projection": "OccLE 10 %, w/o Proj.",
    "primary_only": "OccLE 10 %, w/o align. (primary pseudo labels only)",
    "teacher_in_fusion": "OccLE 10 %, w/ geometric teacher in Phase III",
    "no_voxel_labels": "OccLE 10 %, w/o voxel labels in Phase III",
    "geometry_teacher": "geometric branch, teacher (Ours-T)",
    "geometry_student": "geometric branch, student (Ours-S, strong aug.)",
    # issue 55: the paper's pieces as options (not in the default rows)
    "paper_protocol": "OccLE 10 %, the paper's protocol (no camera mask, class-frequency CE)",
    "geometry_own_encoders": "OccLE 10 %, the geometric branch's own encoders",
    "mamba_4_stages": "OccLE 10 %, 4-stage Dual Mamba",
}
#: The rows of the paper's tables (the default ``--rows``); the others are this project's options.
OPTION_ROWS = ("paper_protocol", "geometry_own_encoders", "mamba_4_stages")
#: The run other rows copy their shared phases from (it trains first).
DONOR = "three_phase_10pct"
#: The paper's numbers (SemanticKITTI val) per table and row, for reference.
PAPER = {
    "tab3": {"three_phase_10pct": "13.94", "primary_only": "9.89"},
    "tab4a": {"full_100pct": "56.77", "geometry_teacher": "52.66", "geometry_student": "53.60"},
    "tab4b": {
        "full_100pct": "20.32 / 51.73",
        "baseline_10pct": "9.64 / 22.30",
        # the rows' check marks are lost in our copy of the paper: these three are 11.84, 8.08 and 11.55 mIoU
        "no_semantic": "one of 11.84, 8.08, 11.55",
        "no_geometric": "one of 11.84, 8.08, 11.55",
        "no_projection": "one of 11.84, 8.08, 11.55",
        "three_phase_10pct": "16.59 / 40.60",
    },
    "tabc2": {
        "teacher_in_fusion": "16.17 / 38.86",
        "no_voxel_labels": "0.37 / 7.84",
        "three_phase_10pct": "16.59 / 40.60",
    },
}


def overrides(name: str, seed: int, args: argparse.Namespace) -> list[str]:
    """The command-line overrides of a row's run (the same for every row, so shared phases compare equal)."""
    out = [
        f"seed={seed}",
        "trainer.enable_progress_bar=false",
        "trainer.deterministic=true",  # bit-reproducible on CPU with the same seed and thread count
        f"data.preset={args.preset}",
        "trainer.check_val_every_n_epoch=100000",  # validate once, at the end of each phase
    ]
    if args.val_scenes is not None:
        out.append(f"data.val_scenes={args.val_scenes}")
    trained = trained_phases(name, args)
    for phase, epochs in trained.items():
        out.append(f"phases.{phase}.trainer.max_epochs={max(1, round(epochs * args.epochs))}")
    out += [f"~phases.{phase}" for phase in base_epochs(name) if phase not in trained]  # past --until
    return [*out, *(item for item in args.set if _phase_of(item) in (None, *trained))]


def _phase_of(item: str) -> str | None:
    """The phase a ``--set`` item changes (``phases.<name>.<key>=...``), else None: it goes to the rows declaring it."""
    parts = item.split("=", 1)[0].strip().split(".")
    return parts[1] if len(parts) > 2 and parts[0] == "phases" else None


_EPOCHS: dict[str, dict[str, int]] = {}


def base_epochs(name: str) -> dict[str, int]:
    """``{phase: trainer.max_epochs}`` of the shipped config."""
    if name not in _EPOCHS:
        from occplug.config import phase_specs
        from occplug.run.runner import load_config

        cfg = load_config([f"occle/{name}"])
        _EPOCHS[name] = {s.name: int(s.config["trainer"]["max_epochs"]) for s in phase_specs(cfg)}
    return _EPOCHS[name]


def partial(name: str, args: argparse.Namespace) -> bool:
    """Whether ``--until`` stops the row before its last phase."""
    return args.until is not None and list(base_epochs(name))[-1] != args.until


def trained_phases(name: str, args: argparse.Namespace) -> dict[str, int]:
    """``base_epochs`` of the phases a row trains: every one, or those up to and including ``--until``."""
    phases = base_epochs(name)
    if not partial(name, args):
        return phases
    names = list(phases)
    return {k: phases[k] for k in names[: names.index(args.until) + 1]}


def run_folder(name: str, seed: int, args: argparse.Namespace) -> Path:
    """Where a row's run trains: ``<row>-seed<N>``, or ``<row>-seed<N>-until-<phase>`` when ``--until`` cuts it."""
    out = Path(args.out) / f"{name}-seed{seed}"
    return out.with_name(f"{out.name}-until-{args.until}") if partial(name, args) else out


def specs(name: str, seed: int, args: argparse.Namespace) -> tuple[dict[str, Any], list[Any]]:
    """The resolved run config of a row and its phases."""
    from occplug.config import phase_specs
    from occplug.run.runner import load_config

    cfg = load_config([f"occle/{name}"], overrides(name, seed, args))
    return cfg, phase_specs(cfg)


def _same(a: Any, b: Any) -> bool:
    return (a.name, a.config, a.freeze, a.init_from, a.pseudo_labels_from) == (
        b.name,
        b.config,
        b.freeze,
        b.init_from,
        b.pseudo_labels_from,
    )


def shared_phases(name: str, seed: int, args: argparse.Namespace) -> list[Any]:
    """The leading phases of a row that equal the donor's (same seed and budget)."""
    if name == DONOR or not args.reuse_phases:
        return []
    _, mine = specs(name, seed, args)
    _, donor = specs(DONOR, seed, args)
    shared = []
    for a, b in zip(mine, donor, strict=False):
        if not _same(a, b):
            break
        shared.append(a)
    return shared


def _copy(src: Path, dst: Path) -> None:
    try:
        shutil.copytree(src, dst, copy_function=os.link)  # hard links: finished phases are never written again
    except OSError:
        shutil.rmtree(dst, ignore_errors=True)
        shutil.copytree(src, dst)


def seed_from_donor(name: str, seed: int, args: argparse.Namespace, out: Path) -> int:
    """Copy the finished phases the row shares with the donor run into ``out``; return how many.

    The donor's whole run is the first source; under ``--until`` its cut run is the second.
    """
    sources = list(dict.fromkeys([Path(args.out) / f"{DONOR}-seed{seed}", run_folder(DONOR, seed, args)]))
    done = []  # (phase spec, the donor folder holding it finished)
    for spec in shared_phases(name, seed, args):
        found = [src for src in sources if (src / spec.name / "DONE").is_file()]
        if not found:
            break
        done.append((spec, found[0]))
    if not done:
        return 0
    import yaml

    cfg, all_specs = specs(name, seed, args)
    out.mkdir(parents=True, exist_ok=True)
    for spec, donor in done:
        _copy(donor / spec.name, out / spec.name)
        if spec.pseudo_labels_from is not None:
            folder = Path("pseudo_labels") / spec.pseudo_labels_from.folder_name
            _copy(donor / folder, out / folder)
    if (done[0][1] / "plugins.json").is_file():
        shutil.copy2(done[0][1] / "plugins.json", out / "plugins.json")
    (out / "config.yaml").write_text(
        "# resolved occplug config with phases; each phase's own config in <phase>/config.yaml\n"
        + yaml.safe_dump(cfg, sort_keys=False, default_flow_style=None)
    )
    if len(done) == len(all_specs):  # nothing left to train: the run's metrics.json from the copied phases
        phases = {s.name: json.loads((out / s.name / "metrics.json").read_text()) for s in all_specs}
        last = all_specs[-1].name
        summary = {**phases[last], "final_phase": last, "phases": phases}
        (out / "metrics.json").write_text(json.dumps(summary, indent=2) + "\n")
    return len(done)


def run(name: str, seed: int, args: argparse.Namespace) -> dict:
    """The run's metrics.json (training it first unless a finished one is there).

    When ``--until`` cuts the row, a finished whole run answers for its leading phases; otherwise the run
    trains in ``<row>-seed<N>-until-<phase>`` (:func:`run_folder`), never in a whole run's folder.
    """
    whole = Path(args.out) / f"{name}-seed{seed}"
    trained = trained_phases(name, args)
    if partial(name, args) and (whole / "metrics.json").is_file():
        summary = json.loads((whole / "metrics.json").read_text())
        if set(trained) <= set(summary.get("phases", {})):
            phases = {k: summary["phases"][k] for k in trained}
            return {**phases[args.until], "final_phase": args.until, "phases": phases}
    out = run_folder(name, seed, args)
    if (out / "metrics.json").is_file():
        summary = json.loads((out / "metrics.json").read_text())
        if set(summary.get("phases", {})) == set(trained):
            return summary
    copied = 0 if (out / "config.yaml").is_file() else seed_from_donor(name, seed, args, out)
    if (out / "metrics.json").is_file():
        print(f"{name} seed {seed}: every phase copied from {DONOR}", file=sys.stderr)
        return json.loads((out / "metrics.json").read_text())
    extra = f" ({copied} phase(s) copied from {DONOR})" if copied else ""
    fit_in_process(f"occle/{name}", overrides(name, seed, args), out, f"{name} seed {seed}{extra}")
    return json.loads((out / "metrics.json").read_text())


def _unmasked(name: str, seed: int, args: argparse.Namespace) -> float:
    """mIoU of the row's final phase re-scored on every voxel (``eval_mask=none``; cached in that phase's folder)."""
    out = run_folder(name, seed, args)
    phases = list(json.loads((out / "metrics.json").read_text())["phases"])
    record = evaluate_in_process(out / phases[-1], "val", ["eval_mask=none"], name="metrics_val_no_mask")
    return float(record.get("mIoU", float("nan")))


def planned_steps(name: str, args: argparse.Namespace) -> dict[str, int]:
    """``{phase: optimizer steps}`` of a row on the synthetic world (before any reuse)."""
    from occplug.data import LabelCut
    from occplug.data.synthetic import preset

    cfg, phases = specs(name, args.seeds[0], args)
    world = preset(args.preset)
    frames = world.train_scenes * world.frames_per_scene
    out = {}
    for spec in phases:
        data = spec.config["data"]
        cut = LabelCut(data.get("label_fraction", 1.0), data.get("subset", "all"))
        batches = math.ceil(len(cut.selected(frames)) / int(data.get("batch_size", 1)))
        out[spec.name] = batches * int(spec.config["trainer"]["max_epochs"])
    return out


def dry_run(args: argparse.Namespace) -> None:
    total = 0
    print(f"world '{args.preset}', epochs x{args.epochs:g}, per seed (seeds {args.seeds}):")
    for name in args.rows:
        steps = planned_steps(name, args)
        shared = {s.name for s in shared_phases(name, args.seeds[0], args)} if DONOR in args.rows else set()
        trained = sum(v for k, v in steps.items() if k not in shared)
        total += trained
        parts = ", ".join(f"{k} {v}{' (copied)' if k in shared else ''}" for k, v in steps.items())
        print(f"  {name:18s} {trained:6d} steps trained: {parts}")
    print(f"total {total} optimizer steps per seed, {total * len(args.seeds)} in all")


def main() -> None:
    parser = argparse.ArgumentParser(
        prog="python -m occplug_occle.tools.ablate",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--rows", nargs="+", default=[r for r in ROWS if r not in OPTION_ROWS], choices=list(ROWS)
    )  # the option rows on request
    parser.add_argument("--epochs", type=float, default=1.0, help="scale every phase's max_epochs (the CPU budget)")
    parser.add_argument("--preset", default="default", help="synthetic world preset (default: default)")
    parser.add_argument("--val-scenes", type=int, default=None, help="validation scenes (default: the preset's)")
    parser.add_argument("--set", nargs="*", default=[], help="extra key=value overrides for every run")
    parser.add_argument("--out", default="runs/occle_ablate")
    parser.add_argument(
        "--results",
        help="also write each row's numbers per seed as small JSONs here (commit them under results/occle/<claim>/)",
    )
    parser.add_argument("--until", help="train each row's phases up to and including this one (e.g. semantic: Tab. 3)")
    parser.add_argument("--dry-run", action="store_true", help="print the planned optimizer steps and stop")
    parser.add_argument(
        "--reuse-phases",
        action="store_true",
        help=f"copy the phases a row shares with {DONOR} of the same seed from that run instead of training them",
    )
    args = parser.parse_args()
    args.rows = sorted(set(args.rows), key=lambda r: (r != DONOR, list(ROWS).index(r)))  # the donor first
    from occplug.config import ConfigError

    try:
        for item in args.set:
            phase = _phase_of(item)
            if phase is not None and not any(phase in base_epochs(r) for r in args.rows):
                raise ConfigError(f"--set {item}: none of the rows {args.rows} declares a phase {phase!r}")
        lacking = [r for r in args.rows if args.until is not None and args.until not in base_epochs(r)]
        if lacking:
            raise ConfigError(f"--until {args.until}: the rows {lacking} have no phase {args.until!r}")
    except ConfigError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if args.dry_run:
        dry_run(args)
        return
    start = time.monotonic()
    commit = code_commit()  # the code the runs start from (the JSON files record it, not a later commit)
    results: dict[str, list[dict]] = {}
    for name in args.rows:  # row by row: an interrupted ablation leaves whole rows
        for seed in args.seeds:
            results.setdefault(name, []).append(run(name, seed, args))

    def values(name: str, key: str, phase: str | None = None) -> list[float]:
        out = []
        for m in results.get(name, []):
            if phase is None and partial(name, args):  # the pipeline's numbers need its last phase
                out.append(float("nan"))
                continue
            src = m if phase is None else m.get("phases", {}).get(phase, {})
            out.append(float(src.get(key, float("nan"))))
        return out

    table: dict[str, dict[str, list[float]]] = {}
    lines = [
        f"seeds {args.seeds}, world '{args.preset}', epochs x{args.epochs:g}, "
        f"val scenes {args.val_scenes or 'preset'}, {time.monotonic() - start:.0f} s",
        "(paper numbers: SemanticKITTI val, for reference only)",
    ]

    def section(title: str, header: list[str], rows: list[tuple[str, list[list[float]], str]]) -> None:
        rows = [r for r in rows if r[0] in results]
        if not rows:
            return
        lines.extend(
            ["", title, "", "| row | " + " | ".join(header) + " | paper |", "|---|" + "--:|" * (len(header) + 1)]
        )
        for name, cols, paper in rows:
            lines.append(f"| {ROWS[name]} | " + " | ".join(mean_std(c) for c in cols) + f" | {paper} |")

    section(
        "Tab. 3 (semantic branch): mIoU of S after Phase I; the pipeline's mIoU / IoU",
        ["mIoU(S)", "mIoU", "IoU"],
        [
            (n, [values(n, "mIoU", "semantic"), values(n, "mIoU"), values(n, "IoU")], f"mIoU(S) {PAPER['tab3'][n]}")
            for n in ("three_phase_10pct", "primary_only")
        ],
    )
    geometry = [("full_100pct", values("full_100pct", "IoU", "teacher"))]
    geometry += [(n, values(n, "IoU")) for n in ("geometry_teacher", "geometry_student")]
    section(
        "Tab. 4(a) (geometric branch): IoU of G (full labels: the teacher of full_100pct)",
        ["IoU(G)"],
        [(n, [v], PAPER["tab4a"][n]) for n, v in geometry],
    )
    whole = not any(partial(n, args) for n in args.rows)
    options = [n for n in (DONOR, *OPTION_ROWS) if n in results and any(o in results for o in OPTION_ROWS)]
    if whole and options:  # every row also scored on every voxel, so paper_protocol's on/off is one protocol
        unmasked = {n: [_unmasked(n, seed, args) for seed in args.seeds] for n in options}
        section(
            "Issue 55: the paper's pieces (mIoU / IoU as the row scores: paper_protocol every voxel, the others "
            "the camera mask; then mIoU on every voxel)",
            ["mIoU", "IoU", "mIoU, no mask"],
            [(n, [values(n, "mIoU"), values(n, "IoU"), unmasked[n]], "—") for n in options],
        )
        for n in options:
            table.setdefault(n, {})["mIoU_no_mask"] = unmasked[n]
    for title, paper in (
        ("Tab. 4(b) (overall pipeline)", PAPER["tab4b"]),
        ("Tab. C.2 (supplementary)", PAPER["tabc2"]),
    ):
        if whole:  # the pipeline's tables need every row's last phase
            section(title, ["mIoU", "IoU"], [(n, [values(n, "mIoU"), values(n, "IoU")], paper[n]) for n in paper])
    for name in results:
        table[name] = table.get(name, {}) | {
            "mIoU": values(name, "mIoU"),
            "IoU": values(name, "IoU"),
            "mIoU_S": values(name, "mIoU", "semantic"),
            "IoU_teacher": values(name, "IoU", "teacher"),
            "IoU_student": values(name, "IoU", "student"),
        }
    ours = statistics.mean(values(DONOR, "mIoU")) if DONOR in results else None
    if not whole:
        ours = None
    if ours is not None and "baseline_10pct" in results:
        base = statistics.mean(values("baseline_10pct", "mIoU"))
        verdict = "PASS" if ours > base else "FAIL"
        lines += ["", f"OccLE at 10 % beats the baseline at 10 % (mIoU {ours:.2f} vs {base:.2f}): {verdict}"]
    if ours is not None and "full_100pct" in results:
        full = statistics.mean(values("full_100pct", "mIoU"))
        share = ours / full * 100 if full > 0 else math.nan
        verdict = "PASS" if full > 0 and ours >= 0.75 * full else "FAIL"
        lines += [
            f"OccLE at 10 % reaches >= 75 % of its full-label mIoU ({ours:.2f} / {full:.2f} = {share:.0f} %): {verdict}"
        ]
    print("\n".join(lines))
    Path(args.out).mkdir(parents=True, exist_ok=True)
    rows = {n: {k: [v if v == v else None for v in vs] for k, vs in cols.items()} for n, cols in table.items()}
    file = "table.json" if args.until is None else f"table-until-{args.until}.json"  # beside the whole runs' table
    (Path(args.out) / file).write_text(json.dumps({"args": vars(args), "rows": rows}, indent=2) + "\n")
    if args.results:
        settings = {"epochs_scale": args.epochs, "preset": args.preset, "val_scenes": args.val_scenes, "set": args.set}
        settings.update(until=args.until, reuse_phases=args.reuse_phases, threads=os.environ.get("OMP_NUM_THREADS"))
        for name, columns in table.items():
            for i, seed in enumerate(args.seeds):
                values = {column: per_seed[i] for column, per_seed in columns.items()}
                row_settings = {**settings, "fit": ["-c", f"occle/{name}", *overrides(name, seed, args)]}
                write_seed_result(args.results, name, seed, values, row_settings, commit=commit)


if __name__ == "__main__":
    main()

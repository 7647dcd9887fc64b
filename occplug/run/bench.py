"""Measuring models side by side on one machine (``occplug bench``; the CLI is :mod:`occplug.cli.bench_cmd`).

Per model: parameters, inference latency per frame (median, min and max of the timed repeats after warm-up),
peak memory of inference and of training (CUDA's peak allocation when the device is CUDA, else the
process's peak resident set size), training step time (forward, backward and optimizer step of
Lightning's loop, data loading excluded; median, min and max) and the accuracy its run directory recorded in
``metrics.json`` (a config has none).

Each model is measured in its own process (a process's peak memory only grows), started as
``python -m occplug.run.bench``. The parent drives every process round by round (:func:`interleave`):
round r of every model runs before round r+1, the order reversed every other round, so a machine
that slows down or speeds up during the benchmark shifts every row alike and the ratios between rows
hold. Protocol: the parent writes the job (one JSON line), then one command per line (``latency``,
``train``, ``stats``); the worker answers one JSON line each.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from occplug.errors import UserError

__all__ = [
    "ACCURACY_KEYS",
    "BenchError",
    "BenchReport",
    "BenchRow",
    "BenchSettings",
    "Spread",
    "Target",
    "code_commit",
    "environment",
    "evaluate_in_process",
    "fit_in_process",
    "interleave",
    "make_row",
    "mean_std",
    "read_accuracy",
    "resolve_target",
    "run_bench",
    "write_seed_result",
    "write_table_seeds",
]

#: The accuracy columns read from a run's ``metrics.json`` (absent ones stay empty).
ACCURACY_KEYS = ("mIoU", "IoU", "RayIoU")
MISSING = "—"


def mean_std(values: Sequence[float], empty: str = MISSING) -> str:
    """``"mean ± std"`` (sample std) of seeds' values for ablation tables, NaN values left out; one value alone
    prints as itself, none as ``empty``."""
    kept = [float(v) for v in values if v == v]
    if not kept:
        return empty
    if len(kept) == 1:
        return f"{kept[0]:.2f}"
    return f"{statistics.mean(kept):.2f} ± {statistics.stdev(kept):.2f}"


def code_commit(path: Path | None = None) -> str | None:
    """The git commit of the code at ``path`` (this package by default), with ``-dirty`` when tracked files have
    uncommitted changes; None outside a git checkout."""
    cwd = Path(path) if path is not None else Path(__file__).resolve().parent

    def git(*args: str) -> str | None:
        try:
            done = subprocess.run(["git", *args], cwd=cwd, capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            return None
        return done.stdout.strip() if done.returncode == 0 else None

    commit = git("rev-parse", "HEAD")
    if commit is None:
        return None
    return commit + ("-dirty" if git("status", "--porcelain", "--untracked-files=no") else "")


def fit_in_process(config: str, overrides: Sequence[str], out: Path, label: str) -> Path:
    """Train ``config`` with ``overrides`` into the run directory ``out`` in an ``occplug fit`` process of its own
    (continuing an interrupted run with ``--resume``), as the ablation and bench scripts train their rows; prints
    ``<label>: trained in <s> s`` to stderr and returns ``out``."""
    command = [sys.executable, "-m", "occplug.cli", "fit", "-c", config, *overrides]
    command += ["--resume", str(out)] if (out / "config.yaml").is_file() else ["--run-dir", str(out)]
    start = time.monotonic()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    print(f"{label}: trained in {time.monotonic() - start:.0f} s", file=sys.stderr)
    return out


def evaluate_in_process(run: Path, split: str = "val", overrides: Sequence[str] = (), name: str | None = None) -> dict:
    """The metrics of ``run``'s ``checkpoints/last.ckpt`` on ``split`` (``val`` or ``test``) with the evaluation-only
    ``overrides``, scored by an ``occplug validate`` / ``occplug test`` process of its own (as the ablation scripts
    re-score a trained run without retraining) and cached as ``run/<name>.json``: by default
    ``metrics_<split>.json``, with overrides ``metrics_<split>_<hash of the overrides>.json``. The cached record
    carries the overrides under ``_eval_set``."""
    if split not in ("val", "test"):
        raise ValueError(f"evaluate_in_process: split must be 'val' or 'test', got {split!r}")
    if name is None:
        tag = hashlib.sha1(" ".join(overrides).encode()).hexdigest()[:8] if overrides else ""
        name = f"metrics_{split}_{tag}" if tag else f"metrics_{split}"
    path = Path(run) / f"{name}.json"
    if not path.is_file():
        command = "validate" if split == "val" else "test"
        ckpt = Path(run) / "checkpoints" / "last.ckpt"
        cli = [sys.executable, "-m", "occplug.cli", command, "--ckpt", str(ckpt), "--json", str(path), *overrides]
        subprocess.run(cli, check=True, stdout=subprocess.DEVNULL)
        record = json.loads(path.read_text())
        path.write_text(json.dumps({**record, "_eval_set": list(overrides)}, indent=2) + "\n")
    return json.loads(path.read_text())


def _program() -> str:
    """How this process was started: ``python -m <module>`` for a module run, else the script's file name."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    return f"python -m {spec.name}" if spec is not None and spec.name else Path(sys.argv[0]).name


def write_seed_result(
    folder: Path | str,
    row: str,
    seed: int,
    values: dict[str, float],
    settings: dict[str, Any],
    commit: str | None = None,
) -> Path:
    """Write one ablation row's numbers for one seed to ``<folder>/<row>-seed<seed>.json`` and return the path.

    The file is small, made to be committed beside a plugin's RESULTS.md, so that a table's mean ± std can be
    checked against the seeds it came from. It records the values, the settings the row ran with (budget, world,
    overrides), the command line, the code's commit (``commit`` where given: a script passes the commit it
    started at, so a commit made while it ran is not recorded; else :func:`code_commit` now) and the numeric
    environment of the process that writes it (:func:`~occplug.run.runner.numeric_environment`: the same code and
    seed reproduce a number bit for bit only on the same CPU kernel set).
    """
    from occplug.run import runner

    path = Path(folder) / f"{row}-seed{seed}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {
        "row": row,
        "seed": seed,
        "values": {k: None if v != v else float(v) for k, v in values.items()},  # NaN (no such class) as null
        "settings": settings,
        "command": [_program(), *sys.argv[1:]],
        "commit": code_commit() if commit is None else commit,
        "environment": runner.numeric_environment(),
    }
    path.write_text(json.dumps(record, indent=2) + "\n")
    return path


def write_table_seeds(
    folder: Path | str, table: dict[str, dict[str, list[float]]], seeds: Sequence[int], settings: dict[str, Any]
) -> list[Path]:
    """:func:`write_seed_result` for every row and seed of an ablation table (``row -> column -> value per seed``,
    in the order of ``seeds``); returns the files written."""
    paths = []
    for row, columns in table.items():
        for i, seed in enumerate(seeds):
            values = {column: per_seed[i] for column, per_seed in columns.items() if i < len(per_seed)}
            paths.append(write_seed_result(folder, row, seed, values, settings))
    return paths


class BenchError(UserError):
    """A bad benchmark input, or a model that could not be measured (one line)."""


@dataclass
class BenchSettings:
    """What every model is measured with."""

    repeats: int = 10
    warmup: int = 3
    train_repeats: int = 5  # 0: inference only (no training rounds; their columns stay empty)
    batch_size: int = 1
    device: str = "auto"
    preset: str | None = None


@dataclass
class Target:
    """One model to measure: a run directory (with its recorded accuracy) or a config."""

    name: str
    source: str
    kind: str  # "run" or "config"
    cfg: dict[str, Any]
    ckpt: str | None = None
    accuracy: dict[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Spread:
    """Minimum, median and maximum of a model's timed repeats (one run's spread: a machine whose speed drifts
    between runs shows it here, beside the median)."""

    min: float
    median: float
    max: float

    @classmethod
    def of(cls, values: Sequence[float]) -> Spread:
        if not values:
            raise ValueError("no timed repeats")
        return cls(min(values), statistics.median(values), max(values))


def _with_spread(median: float | None, low: float | None, high: float | None, digits: int) -> str:
    if median is None:
        return MISSING
    if low is None or high is None:
        return f"{median:.{digits}f}"
    return f"{median:.{digits}f} ({low:.{digits}f}–{high:.{digits}f})"


@dataclass
class BenchRow:
    """One table row. Times in milliseconds (medians; ``*_min_ms`` / ``*_max_ms`` their spread over the
    repeats, None in reports written before they were recorded), memory in MiB; accuracy in percent (None: not
    recorded)."""

    model: str
    source: str
    params: int
    latency_ms: float
    memory_mib: float
    train_step_ms: float | None
    train_memory_mib: float | None
    mIoU: float | None = None
    IoU: float | None = None
    RayIoU: float | None = None
    eval_mask: str | None = None
    latency_min_ms: float | None = None
    latency_max_ms: float | None = None
    train_step_min_ms: float | None = None
    train_step_max_ms: float | None = None


@dataclass
class BenchReport:
    """The table and its header (machine, device, versions, settings)."""

    machine: str
    device: str
    versions: dict[str, str]
    settings: dict[str, Any]
    rows: list[BenchRow]

    # ------------------------------------------------------------------ JSON
    def to_json(self) -> str:
        return json.dumps(asdict(self), indent=2) + "\n"

    @classmethod
    def from_json(cls, text: str) -> BenchReport:
        data = json.loads(text)
        return cls(**{**data, "rows": [BenchRow(**r) for r in data["rows"]]})

    # ------------------------------------------------------------------ CSV
    def to_csv(self) -> str:
        """``# key: value`` header lines (settings and versions as JSON), then one row per model."""
        out = io.StringIO()
        out.write(f"# machine: {self.machine}\n# device: {self.device}\n")
        out.write(f"# versions: {json.dumps(self.versions)}\n# settings: {json.dumps(self.settings)}\n")
        writer = csv.writer(out, lineterminator="\n")
        names = [f.name for f in fields(BenchRow)]
        writer.writerow(names)
        for row in self.rows:
            writer.writerow([MISSING if getattr(row, n) is None else getattr(row, n) for n in names])
        return out.getvalue()

    @classmethod
    def from_csv(cls, text: str) -> BenchReport:
        header: dict[str, str] = {}
        lines = text.splitlines()
        while lines and lines[0].startswith("# "):
            key, _, value = lines.pop(0)[2:].partition(": ")
            header[key] = value
        types = {f.name: f.type for f in fields(BenchRow)}
        rows = []
        for raw in csv.DictReader(lines):
            values: dict[str, Any] = {}
            for key, text_value in raw.items():
                kind = str(types[key])
                if text_value == MISSING:
                    values[key] = None
                elif kind.startswith("int"):
                    values[key] = int(text_value)
                elif kind.startswith("float"):
                    values[key] = float(text_value)
                else:
                    values[key] = text_value
            rows.append(BenchRow(**values))
        return cls(
            machine=header["machine"],
            device=header["device"],
            versions=json.loads(header["versions"]),
            settings=json.loads(header["settings"]),
            rows=rows,
        )

    # ------------------------------------------------------------------ Markdown
    def to_markdown(self) -> str:
        s = self.settings
        memory = "peak CUDA allocation" if self.device.startswith("cuda") else "peak RSS of the model's process"
        lines = [
            f"machine: {self.machine}",
            f"device: {self.device}",
            "versions: " + ", ".join(f"{k} {v}" for k, v in self.versions.items()),
            f"batch size {s['batch_size']}; latency: median (min–max) of {s['repeats']} interleaved repeats after "
            f"{s['warmup']} warm-up, per frame; train step: "
            + (f"median (min–max) of {s['train_repeats']}" if s["train_repeats"] else "not measured")
            + f"; memory: {memory}",
            "",
            "| model | params | latency (ms/frame) | memory (MiB) | train step (ms) | train memory (MiB) "
            "| mIoU | IoU | RayIoU | eval mask |",
            "|---|--:|--:|--:|--:|--:|--:|--:|--:|---|",
        ]
        for r in self.rows:
            acc = [MISSING if v is None else f"{v:.2f}" for v in (r.mIoU, r.IoU, r.RayIoU)]
            latency = _with_spread(r.latency_ms, r.latency_min_ms, r.latency_max_ms, 2)
            step = _with_spread(r.train_step_ms, r.train_step_min_ms, r.train_step_max_ms, 1)
            train_memory = MISSING if r.train_memory_mib is None else f"{r.train_memory_mib:.0f}"
            lines.append(
                f"| {r.model} | {_params(r.params)} | {latency} | {r.memory_mib:.0f} | {step} "
                f"| {train_memory} | {' | '.join(acc)} | {r.eval_mask or MISSING} |"
            )
        return "\n".join(lines) + "\n"


def _params(n: int) -> str:
    return f"{n / 1e6:.2f} M" if n >= 10_000 else str(n)


# ---------------------------------------------------------------------- inputs
def read_accuracy(metrics: dict[str, Any]) -> dict[str, Any]:
    """``{mIoU, IoU, RayIoU, eval_mask}`` of a run's ``metrics.json`` (a metric's prefixed key,
    e.g. ``occ3d_miou/mIoU``, when two metrics share the name; None where not recorded)."""
    out: dict[str, Any] = {}
    for key in ACCURACY_KEYS:
        value = metrics.get(key)
        if value is None:
            value = next((v for k, v in metrics.items() if k.endswith(f"/{key}") and v is not None), None)
        out[key] = None if value is None else float(value)
    out["eval_mask"] = metrics.get("eval_mask")
    return out


def resolve_target(ref: str, settings: BenchSettings, overrides: Sequence[str] = ()) -> Target:
    """A run directory (``config.yaml``, optional ``metrics.json`` and ``checkpoints/last.ckpt``) or a config.

    Raises:
        BenchError: a missing path, a folder that is no run directory, a bad config (one line).
    """
    from occplug.run import runner

    path = Path(ref)
    common = [*overrides, f"data.batch_size={settings.batch_size}"]
    try:
        if path.is_dir():
            config = path / "config.yaml"
            if not config.is_file():
                raise BenchError(f"{ref}: a folder but not an occplug run directory (no config.yaml)")
            cfg = runner.load_config([], common, saved=yaml.safe_load(config.read_text()))
            metrics_path = path / "metrics.json"
            accuracy = read_accuracy(json.loads(metrics_path.read_text())) if metrics_path.is_file() else {}
            last = path / "checkpoints" / "last.ckpt"
            name = path.resolve().name
            return Target(name, ref, "run", cfg, str(last) if last.is_file() else None, accuracy)
        if not path.exists() and (path.suffix in (".yaml", ".yml") or path.parent.exists() and os.sep in ref):
            raise BenchError(f"{ref}: no such run directory or config file")
        preset = [f"data.preset={settings.preset}"] if settings.preset else []
        cfg = runner.load_config([ref], [*common, *preset])
    except json.JSONDecodeError as exc:
        raise BenchError(f"{ref}/metrics.json: not valid JSON ({exc.msg})") from None
    except (yaml.YAMLError, OSError) as exc:
        raise BenchError(f"{ref}: cannot be read ({str(exc).splitlines()[0]})") from None
    except runner.RunError as exc:
        raise BenchError(f"{ref}: {exc}") from None
    except UserError as exc:
        if isinstance(exc, BenchError):
            raise
        raise BenchError(f"{ref}: {exc}") from None
    return Target(path.stem if path.is_file() else ref, ref, "config", cfg)  # a file: its stem; a reference as given


def environment(device: str) -> tuple[str, str, dict[str, str]]:
    """``(machine, device, versions)`` for the report's header."""
    import lightning
    import torch

    from occplug.run import runner

    cpu = runner.cpu_name()
    mem = ""
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        mem = f", {pages / 2**30:.0f} GiB RAM"
    except (ValueError, OSError, AttributeError):
        pass
    machine = f"{platform.node()}: {cpu}, {os.cpu_count()} cores{mem}, {platform.system()} {platform.machine()}"
    if device.startswith("cuda"):
        props = torch.cuda.get_device_properties(0)
        shown = f"{device} {props.name} ({props.total_memory / 2**30:.0f} GiB, CUDA {torch.version.cuda})"
    else:
        shown = f"cpu ({torch.get_num_threads()} torch threads)"
    from importlib.metadata import PackageNotFoundError, version

    try:
        occplug_version = version("occplug")
    except PackageNotFoundError:
        occplug_version = "source"
    versions = {
        "python": platform.python_version(),
        "torch": torch.__version__,
        "lightning": lightning.__version__,
        "occplug": occplug_version,
    }
    versions.update({f"plugin {k}": str(v) for k, v in runner.plugin_versions().items()})
    return machine, shown, versions


def pick_device(device: str) -> str:
    """``auto``: CUDA when present, else CPU."""
    import torch

    if device == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise BenchError(f"--device {device}: CUDA is not available on this machine")
    if device != "cpu" and not device.startswith("cuda"):
        raise BenchError(f"--device {device}: expected auto, cpu or cuda")
    return device


# ---------------------------------------------------------------------- the parent
class _Worker:
    """One model's measuring process."""

    def __init__(self, target: Target, job: dict[str, Any]) -> None:
        self.name = target.name
        self._log = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "occplug.run.bench"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=self._log,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        self._send(json.dumps(job))

    def _send(self, line: str) -> None:
        assert self.proc.stdin is not None
        try:
            self.proc.stdin.write(line + "\n")
            self.proc.stdin.flush()
        except BrokenPipeError:
            pass  # the answer's EOF reports it

    def read(self) -> dict[str, Any]:
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        if not line:
            self.proc.wait()
            self._log.seek(0)
            tail = [t for t in self._log.read().splitlines() if t.strip()]
            raise BenchError(f"{self.name}: the measuring process ended ({tail[-1] if tail else 'no output'})")
        answer = json.loads(line)
        if "error" in answer:
            raise BenchError(f"{self.name}: {answer['error']}")
        return answer

    def request(self, command: str) -> dict[str, Any]:
        self._send(command)
        return self.read()

    def close(self) -> None:
        if self.proc.poll() is None:
            self._send("quit")
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


def interleave(workers: Sequence[Any], command: str, rounds: int) -> list[list[float]]:
    """Run ``rounds`` rounds of ``command`` on every worker; ``[worker][round]`` of the answers' ``ms``.

    Round r of every worker runs before round r+1, in the workers' order on even rounds and in
    reverse on odd ones (so neither the first nor the last place of a round favours one model).
    """
    out: list[list[float]] = [[] for _ in workers]
    for r in range(rounds):
        order = range(len(workers)) if r % 2 == 0 else reversed(range(len(workers)))
        for i in order:
            out[i].append(float(workers[i].request(command)["ms"]))
    return out


def run_bench(
    targets: Sequence[Target], settings: BenchSettings, progress: Callable[[str], None] | None = None
) -> BenchReport:
    """Measure every target in its own process, interleaved; the report with its header."""
    device = pick_device(settings.device)
    machine, shown_device, versions = environment(device)
    workers: list[_Worker] = []
    try:
        for t in targets:
            job = {**asdict(settings), "cfg": t.cfg, "ckpt": t.ckpt, "device": device}
            workers.append(_Worker(t, job))
        ready = [w.read() for w in workers]  # built and warmed up, in parallel
        if progress:
            progress(f"measuring {len(workers)} model(s): {settings.repeats} latency rounds")
        latency = interleave(workers, "latency", settings.repeats)
        if progress:
            progress(f"{settings.train_repeats} training rounds")
        train = interleave(workers, "train", settings.train_repeats) if settings.train_repeats else [[]] * len(workers)
        stats = [w.request("stats") for w in workers]
    finally:
        for w in workers:
            w.close()
    rows = [make_row(*parts) for parts in zip(targets, ready, latency, train, stats, strict=True)]
    shown = {k: v for k, v in asdict(settings).items() if k not in ("device",)}
    return BenchReport(machine, shown_device, versions, shown, rows)


def make_row(
    target: Target, info: dict[str, Any], latency: Sequence[float], train: Sequence[float], stats: dict[str, Any]
) -> BenchRow:
    """A model's row from its worker's answers: ``info`` (``params``), the timed ``latency`` and ``train``
    repeats in ms (:func:`interleave`; no ``train`` repeats: inference only) and ``stats`` (peak memory in
    bytes)."""
    lat = Spread.of(latency)
    step = Spread.of(train) if train else None
    acc = target.accuracy
    return BenchRow(
        model=target.name,
        source=target.source,
        params=int(info["params"]),
        latency_ms=lat.median,
        memory_mib=stats["memory"] / 2**20,
        train_step_ms=step.median if step else None,
        train_memory_mib=stats["train_memory"] / 2**20 if step else None,
        mIoU=acc.get("mIoU"),
        IoU=acc.get("IoU"),
        RayIoU=acc.get("RayIoU"),
        eval_mask=acc.get("eval_mask") if target.kind == "run" else None,
        latency_min_ms=lat.min,
        latency_max_ms=lat.max,
        train_step_min_ms=step.min if step else None,
        train_step_max_ms=step.max if step else None,
    )


# ---------------------------------------------------------------------- the worker
def _peak_rss() -> int:
    import resource

    scale = 1 if sys.platform == "darwin" else 1024  # ru_maxrss: bytes on macOS, KiB on Linux
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * scale


def _worker_main() -> int:
    """A measuring process: read the job, build the model, answer commands (see the module docstring)."""
    proto = os.fdopen(os.dup(1), "w", buffering=1)
    os.dup2(2, 1)  # anything else printed (Lightning, plugins) goes to the log, not the protocol
    sys.stdout = sys.stderr

    def answer(payload: dict[str, Any]) -> None:
        proto.write(json.dumps(payload) + "\n")
        proto.flush()

    try:
        _serve(json.loads(sys.stdin.readline()), answer)
    except Exception as exc:
        text = str(exc).strip()
        answer({"error": text.splitlines()[0] if text else type(exc).__name__})
        return 1
    return 0


def _serve(job: dict[str, Any], answer: Callable[[dict[str, Any]], None]) -> None:
    import torch
    from lightning.pytorch.callbacks import Callback

    from occplug.run import runner

    device = torch.device(job["device"])
    cuda = device.type == "cuda"

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize(device)

    cfg = job["cfg"]
    torch.manual_seed(int(cfg.get("seed", 0)))
    if job["ckpt"]:
        dm, model = runner.restore_run(cfg, runner.load_checkpoint(Path(job["ckpt"])), Path(job["ckpt"]))
    else:
        dm, model = runner.build_run(cfg)
    dataset = dm.dataset("val")
    count = min(int(job["batch_size"]), len(dataset))
    batch = dm.collate([dataset[i] for i in range(count)]).to(device)
    model.to(device).eval()
    if cuda:
        torch.cuda.reset_peak_memory_stats(device)

    def infer() -> float:
        sync()
        start = time.perf_counter()
        with torch.inference_mode():
            model.predict_occupancy(batch)
        sync()
        return (time.perf_counter() - start) * 1000.0 / count

    for _ in range(int(job["warmup"])):
        infer()
    answer({"ready": True, "params": sum(p.numel() for p in model.parameters())})

    memory: dict[str, int] = {}
    commands = iter(lambda: sys.stdin.readline().strip(), "")
    timer: dict[str, float] = {}

    class StepTimer(Callback):
        """Times measured training steps, each on the parent's ``train`` command (the first already read)."""

        def __init__(self) -> None:
            self.step = 0
            self.pending = True

        def on_train_batch_start(self, trainer, pl_module, batch, batch_idx) -> None:  # type: ignore[override]
            if self.step >= int(job["warmup"]):
                if not self.pending and next(commands, "quit") != "train":
                    raise SystemExit(0)
                self.pending = False
                sync()
                timer["start"] = time.perf_counter()

        def on_train_batch_end(self, trainer, pl_module, outputs, batch, batch_idx) -> None:  # type: ignore[override]
            if self.step >= int(job["warmup"]):
                sync()
                answer({"ms": (time.perf_counter() - timer["start"]) * 1000.0})
            self.step += 1

    for command in commands:
        if command == "latency":
            answer({"ms": infer()})
        elif command == "train":
            memory["memory"] = torch.cuda.max_memory_allocated(device) if cuda else _peak_rss()
            if cuda:
                torch.cuda.reset_peak_memory_stats(device)
            _train(cfg, dm, model, job, StepTimer())
            memory["train_memory"] = torch.cuda.max_memory_allocated(device) if cuda else _peak_rss()
        elif command == "stats":
            memory.setdefault("memory", torch.cuda.max_memory_allocated(device) if cuda else _peak_rss())
            memory.setdefault("train_memory", memory["memory"])
            answer(memory)
        elif command == "quit":
            return
        else:
            raise ValueError(f"unknown command {command!r}")


#: Trainer settings that change what one training step computes; the rest is the benchmark's own.
_STEP_KEYS = ("precision", "gradient_clip_val", "gradient_clip_algorithm", "deterministic", "benchmark")


def _train(cfg: dict[str, Any], dm: Any, model: Any, job: dict[str, Any], timer: Any) -> None:
    from occplug.run import runner

    given = cfg.get("trainer") or {}
    trainer_cfg = {k: given[k] for k in _STEP_KEYS if k in given}
    trainer_cfg.update(
        accelerator="gpu" if job["device"].startswith("cuda") else "cpu",
        devices=1,
        max_epochs=-1,
        max_steps=int(job["warmup"]) + int(job["train_repeats"]),
        limit_val_batches=0,
        num_sanity_val_steps=0,
        enable_checkpointing=False,
        enable_progress_bar=False,
        enable_model_summary=False,
        log_every_n_steps=1,
    )
    model.train()
    # a few steps read a few frames (a synthetic world generates them on access): never generate the whole split
    dm.prepare_data = lambda: None
    with tempfile.TemporaryDirectory(prefix="occplug-bench-") as root:
        trainer = runner._trainer({**cfg, "trainer": trainer_cfg, "callbacks": None}, Path(root), [timer], False)
        trainer.fit(model, datamodule=dm)


if __name__ == "__main__":
    raise SystemExit(_worker_main())

"""`rgbdnav batch`: one `map` / `localize` / `eval` task per source on a Dask cluster.

Each task calls the verb's own function (:func:`~rgbdnav.runners.map.run_map`,
:func:`~rgbdnav.runners.localize.run_localize`, :func:`~rgbdnav.runners.eval.run_eval` /
``run_relations_eval``) in a worker process, writing ``DIR/<source-name>/`` exactly as the single
verb would, and returns one row: status, accuracy against ground truth where the source has one
(the simulator's truth, or Kümmerle relations in ``<log-name>.relations`` beside a CARMEN log),
wall time and the task's peak memory. Any failure of a source becomes its row's one-line error;
the batch goes on. A finished source leaves ``batch.json`` (its row) in its folder, written last:
a rerun skips it and counts it. ``DIR/report.md`` and ``DIR/report.json`` are rewritten
atomically after every finished source, so an interrupted batch still has its report.

The cluster is a :class:`distributed.LocalCluster` of single-threaded worker processes (one per
core, at most one per source) unless ``--scheduler`` names a running one, whose workers must be
able to import rgbdnav and read the sources.
"""

from __future__ import annotations

import json
import logging
import os
import resource
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from sensors.atomic import atomic_write_text
from sensors.types import ConfigError, RgbdNavError

log = logging.getLogger(__name__)

VERBS = ("map", "localize", "eval")
ROW_FILE = "batch.json"  # a source's row, written when its task is done: the resume marker
SOURCE_SUFFIXES = (".gz", ".clf", ".log", ".yaml", ".yml", ".tum", ".txt")


@dataclass(frozen=True)
class BatchOptions:
    """What every task of one batch shares (the single verbs' options)."""

    verb: str
    out: Path
    config_files: tuple[Path, ...] = ()
    overrides: tuple[str, ...] = ()
    map_bundle: Path | None = None  # localize
    reference: Path | None = None  # eval: TUM reference ...
    relations: Path | None = None  # ... or Kümmerle relations
    align: str = "se3"  # eval
    seed: int = 0  # world sources
    force_3dof: bool = False


@dataclass(frozen=True)
class Task:
    source: Path
    name: str
    opts: BatchOptions

    @property
    def folder(self) -> Path:
        return self.opts.out / self.name


@dataclass
class BatchResult:
    rows: list[dict[str, Any]] = field(default_factory=list)
    skipped: int = 0

    @property
    def failed(self) -> int:
        return sum(r["status"] == "failed" for r in self.rows)


def source_name(source: Path) -> str:
    """The folder name of a source: its file name without log/world suffixes; a run's
    ``trajectory.tum`` is named after its run folder."""
    if source.name == "trajectory.tum":
        return source.parent.name
    name = source.name
    while Path(name).suffix in SOURCE_SUFFIXES:
        name = Path(name).stem
    return name or source.name


def relations_beside(source: Path) -> Path | None:
    """``NAME.relations`` beside a log ``NAME.clf`` / ``NAME.log.gz``: its Kümmerle ground truth."""
    candidate = source.parent / f"{source_name(source)}.relations"
    return candidate if source.is_file() and candidate.is_file() else None


def one_line(err: BaseException) -> str:
    """An error as one line: known errors by their message, others with their type."""
    text = " ".join(str(err).split()) or type(err).__name__
    return text if isinstance(err, RgbdNavError) else f"{type(err).__name__}: {text}"


# 1. The task (runs in a worker process) -----------------------------------------------------


def _reset_peak_rss() -> bool:
    """Reset the process's peak RSS (Linux ``clear_refs`` 5) so it measures this task alone."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _peak_rss_mb() -> float:
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)


def _read_summary(folder: Path) -> dict[str, Any]:
    return json.loads((folder / "summary.json").read_text())


def _relations_accuracy(trajectory: Path, relations: Path, out: Path) -> dict[str, Any]:
    from rgbdnav.runners.eval import run_relations_eval

    try:
        s = run_relations_eval(trajectory, relations, out)
    except RgbdNavError as err:
        return {"relations": str(relations), "relations_error": one_line(err)}
    r = s["relations_error"]
    return {
        "relations": str(relations),
        "relations_scored": r["count"],
        "rel_trans_mean_m": r["trans_mean_m"],
        "rel_rot_mean_deg": r["rot_mean_deg"],
    }


def map_accuracy(summary: dict[str, Any]) -> dict[str, Any]:
    """A map run's scores against the simulator's truth: ATE, and the grid's IoU with the floor
    plan unless nothing was there to compare (no wall mapped, none seen: 0/0 is no score)."""
    acc: dict[str, Any] = {}
    truth = summary.get("slam_vs_groundtruth") or {}
    if "ate_rmse_m" in truth:
        acc = {"ate_rmse_m": truth["ate_rmse_m"], "ate_rmse_aligned_m": truth["ate_rmse_aligned_m"]}
    plan = summary.get("grid_vs_floor_plan") or {}
    if plan.get("true_positive", 0) + plan.get("false_positive", 0) + plan.get("false_negative", 0):
        acc["grid_iou"] = plan["iou"]
    return acc


def _run_map(task: Task) -> dict[str, Any]:
    from rgbdnav.cache import recording_for
    from rgbdnav.config import load_config
    from rgbdnav.runners.map import run_map

    o = task.opts
    cfg = load_config(list(o.config_files), list(o.overrides))
    recording = recording_for(task.source, cfg, o.seed)
    run_map(recording, task.folder, o.config_files, o.overrides, force_3dof=o.force_3dof)
    acc = map_accuracy(_read_summary(task.folder))
    if (rel := relations_beside(task.source)) is not None:
        acc |= _relations_accuracy(task.folder / "trajectory.tum", rel, task.folder / "relations")
    return acc


def _run_localize(task: Task) -> dict[str, Any]:
    from rgbdnav.cache import recording_for
    from rgbdnav.config import load_config
    from rgbdnav.runners.localize import run_localize

    o = task.opts
    assert o.map_bundle is not None  # checked before any task starts
    cfg = load_config(list(o.config_files), list(o.overrides))
    recording = recording_for(task.source, cfg, o.seed)
    _, summary = run_localize(
        recording, o.map_bundle, task.folder, o.config_files, o.overrides, force_3dof=o.force_3dof
    )
    c = summary["counts"]
    acc: dict[str, Any] = {"tracked": f"{c['tracking']}/{c['scans']}"}
    truth = summary.get("vs_groundtruth") or {}
    if truth.get("matched"):
        acc |= {
            "position_error_median_m": truth["position_error_m"]["median"],
            "tracked_but_wrong": truth["tracked_but_wrong"],
        }
    if (rel := relations_beside(task.source)) is not None and c["tracking"]:
        acc |= _relations_accuracy(task.folder / "trajectory.tum", rel, task.folder / "relations")
    return acc


def _run_eval(task: Task) -> dict[str, Any]:
    from rgbdnav.runners.eval import run_eval, run_relations_eval

    o = task.opts
    if o.reference is not None:
        s = run_eval(
            task.source,
            o.reference,
            task.folder,
            align=o.align,
            config_files=o.config_files,
            overrides=o.overrides,
        )
        return {k: s[k] for k in ("ate_rmse_m", "rpe_trans_rmse_m", "rpe_rot_rmse_deg") if k in s}
    assert o.relations is not None  # checked before any task starts
    s = run_relations_eval(
        task.source, o.relations, task.folder, config_files=o.config_files, overrides=o.overrides
    )
    return {
        "relations_scored": s["relations_error"]["count"],
        "rel_trans_mean_m": s["rel_trans_mean_m"],
        "rel_rot_mean_deg": s["rel_rot_mean_deg"],
    }


RUNNERS: dict[str, Callable[[Task], dict[str, Any]]] = {
    "map": _run_map,
    "localize": _run_localize,
    "eval": _run_eval,
}


def run_task(task: Task) -> dict[str, Any]:
    """Run one source; its row. Never raises for the source's own failures."""
    scoped = _reset_peak_rss()
    t0 = time.perf_counter()
    row: dict[str, Any] = {
        "source": str(task.source),
        "name": task.name,
        "verb": task.opts.verb,
        "status": "done",
        "accuracy": {},
        "error": None,
    }
    try:
        row["accuracy"] = RUNNERS[task.opts.verb](task)
    except Exception as err:  # noqa: BLE001 - any failure of one source is that source's row
        log.debug("source %s failed", task.source, exc_info=True)
        row.update(status="failed", error=one_line(err))
    row["wall_s"] = round(time.perf_counter() - t0, 2)
    row["peak_rss_mb"] = _peak_rss_mb()
    row["peak_rss_scope"] = "task" if scoped else "worker process"
    row["worker_pid"] = os.getpid()
    if row["status"] == "done":
        atomic_write_text(task.folder / ROW_FILE, json.dumps(row, indent=2) + "\n")
    return row


# 2. The batch (runs in the CLI process) ------------------------------------------------------


def finished_row(task: Task) -> dict[str, Any] | None:
    """The row a previous batch left for this source and verb, or None if it must run."""
    try:
        row = json.loads((task.folder / ROW_FILE).read_text())
        summary = _read_summary(task.folder)
    except (OSError, ValueError):
        return None
    same = row.get("verb") == task.opts.verb and row.get("source") == str(task.source)
    return row if same and row.get("status") == "done" and isinstance(summary, dict) else None


def plan(sources: Sequence[Path], opts: BatchOptions) -> list[Task]:
    """Check the batch before any work: verb, its inputs, sources present and named apart."""
    if opts.verb not in VERBS:
        raise ConfigError(f"batch {opts.verb!r}: use one of {', '.join(VERBS)}")
    if not sources:
        raise ConfigError("batch: give at least one source")
    if opts.verb == "localize" and opts.map_bundle is None:
        raise ConfigError("batch localize needs --map MAP (the map every source is localised in)")
    if opts.verb == "eval" and (opts.reference is None) == (opts.relations is None):
        raise ConfigError("batch eval needs exactly one of --reference GT and --relations FILE")
    if opts.verb != "eval" and (opts.reference or opts.relations):
        raise ConfigError(
            "--reference / --relations are for batch eval (map and localize use "
            "NAME.relations beside a log)"
        )
    for extra in (opts.map_bundle, opts.reference, opts.relations):
        if extra is not None and not extra.exists():
            raise ConfigError(f"{extra}: no such file or folder")
    # Absolute paths: a worker's working directory is not necessarily ours.
    opts = replace(
        opts,
        out=opts.out.absolute(),
        config_files=tuple(p.absolute() for p in opts.config_files),
        map_bundle=opts.map_bundle.absolute() if opts.map_bundle else None,
        reference=opts.reference.absolute() if opts.reference else None,
        relations=opts.relations.absolute() if opts.relations else None,
    )
    tasks: dict[str, Task] = {}
    for source in (s.absolute() for s in sources):
        name = source_name(source)
        if name in tasks:
            raise ConfigError(
                f"two sources would write {opts.out / name}: {tasks[name].source} "
                f"and {source}; rename one"
            )
        tasks[name] = Task(source, name, opts)
    return list(tasks.values())


def default_workers(n_tasks: int) -> int:
    """One single-threaded worker per core (mapping is CPU-bound), never more than tasks."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return max(1, min(n_tasks, cores or 1))


def _client(scheduler: str | None, workers: int) -> Any:
    try:
        from distributed import Client, LocalCluster
    except ImportError:
        raise ConfigError("batch needs Dask: pip install 'rgbdnav[batch]'") from None
    if scheduler is not None:
        try:
            return Client(scheduler, timeout="10s")
        except (OSError, TimeoutError, ValueError) as err:  # unreachable, malformed
            raise ConfigError(
                f"--scheduler {scheduler}: cannot connect ({one_line(err)})"
            ) from None
    # Dask's own chatter (start-up, and a heartbeat racing the shutdown) is not the user's
    # business; each source's failure is in its row. --verbose shows it.
    quiet = not log.isEnabledFor(logging.DEBUG)
    logging.getLogger("distributed").setLevel(logging.ERROR if quiet else logging.INFO)
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",  # a free port: batches side by side do not clash
        silence_logs=logging.CRITICAL if quiet else logging.WARNING,
    )
    return Client(cluster)


def run_batch(
    sources: Sequence[Path],
    opts: BatchOptions,
    scheduler: str | None = None,
    workers: int | None = None,
    on_row: Callable[[dict[str, Any]], None] | None = None,
) -> BatchResult:
    """Run every source not finished before; write the report after each one. Its rows, in the
    order of ``sources``."""
    tasks = plan(sources, opts)
    if workers is not None and workers < 1:
        raise ConfigError(f"--workers must be >= 1, got {workers}")
    opts = tasks[0].opts  # with absolute paths
    opts.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    rows: dict[str, dict[str, Any]] = {}
    todo: list[Task] = []
    for task in tasks:
        if (row := finished_row(task)) is not None:
            rows[task.name] = {**row, "resumed": True}
            if on_row is not None:
                on_row(rows[task.name])
        else:
            todo.append(task)
    skipped = len(tasks) - len(todo)
    n_workers = workers or default_workers(len(todo))
    meta = {
        "verb": opts.verb,
        "scheduler": scheduler or f"LocalCluster, {n_workers} worker(s)",
        "sources": len(tasks),
        "skipped_as_done": skipped,
    }

    def report() -> None:
        ordered = [rows[t.name] for t in tasks if t.name in rows]
        write_report(opts.out, {**meta, "wall_s": round(time.perf_counter() - t0, 2)}, ordered)

    report()
    if todo:
        client = _client(scheduler, n_workers)
        from distributed import as_completed

        try:
            futures = {
                client.submit(
                    run_task,
                    t,
                    pure=False,
                    key=f"{opts.verb}-{t.name}-{os.getpid()}-{time.time_ns()}",
                ): t
                for t in todo
            }
            for fut in as_completed(futures):
                task = futures[fut]
                try:
                    row = fut.result()
                except Exception as err:  # noqa: BLE001 - a lost worker fails its source only
                    row = {
                        "source": str(task.source),
                        "name": task.name,
                        "verb": opts.verb,
                        "status": "failed",
                        "accuracy": {},
                        "error": one_line(err),
                    }
                rows[task.name] = row
                report()
                if on_row is not None:
                    on_row(row)
        finally:
            cluster = client.cluster
            client.close()
            if cluster is not None and scheduler is None:
                cluster.close()
    report()
    return BatchResult([rows[t.name] for t in tasks], skipped)


# 3. The report -------------------------------------------------------------------------------


def accuracy_text(acc: dict[str, Any]) -> str:
    """The accuracy cell: the numbers a reader compares across sources."""
    parts = []
    if "ate_rmse_m" in acc:
        parts.append(f"ATE {acc['ate_rmse_m']:.3f} m")
    if "grid_iou" in acc:
        parts.append(f"grid IoU {acc['grid_iou']:.2f}")
    if "rpe_trans_rmse_m" in acc:
        parts.append(f"RPE {acc['rpe_trans_rmse_m']:.3f} m")
    if "rel_trans_mean_m" in acc:
        parts.append(
            f"REL {acc['rel_trans_mean_m']:.3f} m / {acc['rel_rot_mean_deg']:.2f}° "
            f"({acc['relations_scored']} rel.)"
        )
    if "relations_error" in acc:
        parts.append(f"relations: {acc['relations_error']}")
    if "tracked" in acc:
        parts.append(f"tracked {acc['tracked']}")
    if acc.get("position_error_median_m") is not None:
        parts.append(f"pos. err. median {acc['position_error_median_m']:.3f} m")
    return "; ".join(parts) or "no ground truth"


def _accuracy_cell(row: dict[str, Any]) -> str:
    return "-" if row["status"] == "failed" else accuracy_text(row["accuracy"])


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


def write_report(out: Path, meta: dict[str, Any], rows: list[dict[str, Any]]) -> None:
    """``report.json`` (everything) and ``report.md`` (one table row per source), atomically."""
    counts = {s: sum(r["status"] == s for r in rows) for s in ("done", "failed")}
    doc = {**meta, "finished": len(rows), **counts, "rows": rows}
    atomic_write_text(out / "report.json", json.dumps(doc, indent=2) + "\n")
    lines = [
        f"# rgbdnav batch {meta['verb']}",
        "",
        f"{len(rows)} of {meta['sources']} sources finished: {counts['done']} done "
        f"({meta['skipped_as_done']} of them skipped as done before), {counts['failed']} failed; "
        f"{meta['scheduler']}, {meta['wall_s']} s.",
        "",
        "| source | status | accuracy | wall [s] | peak RSS [MB] | error |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        status = "done (earlier)" if r.get("resumed") else r["status"]
        lines.append(
            f"| {_cell(r['name'])} | {status} | {_cell(_accuracy_cell(r))} "
            f"| {r.get('wall_s', '-')} | {r.get('peak_rss_mb', '-')} "
            f"| {_cell(r['error'] or '')} |"
        )
    atomic_write_text(out / "report.md", "\n".join(lines) + "\n")


__all__ = ["BatchOptions", "BatchResult", "Task", "run_batch", "run_task", "source_name"]

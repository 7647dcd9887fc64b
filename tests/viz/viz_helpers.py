"""Constants and hand-built grids shared by the picture tests."""

from __future__ import annotations

import torch

from occplug.geometry import GridSpec

FREE = 17
CAR, TRUCK, ROAD, BUILDING = 4, 10, 11, 15


def small_grid() -> GridSpec:
    """A small grid: 20 x 16 x 8 voxels of 0.5 m, x in [-5, 5), y in [-4, 4), z in [-1, 3)."""
    return GridSpec((-5.0, -4.0, -1.0, 5.0, 4.0, 3.0), 0.5)


def empty(grid: GridSpec) -> torch.Tensor:
    """An all-free ``(X, Y, Z)`` uint8 label grid."""
    return torch.full(grid.shape, FREE, dtype=torch.uint8)


def read_rrd(path) -> dict[str, dict]:
    """Read a ``.rrd`` back with rerun's own reader.

    Returns ``{entity path: {"frames": set of 'frame' timeline values, "columns": set of column
    names, "lengths": {column: [instances per row]}}}``. Uses ``rerun.chunk.RrdReader`` (rerun-sdk
    >= 0.3x) or, on older SDKs, ``rerun.dataframe.load_recording``.
    """
    try:
        from rerun.chunk import RrdReader
    except ImportError:  # older rerun-sdk: the dataframe API
        return _read_rrd_dataframe(path)
    out: dict[str, dict] = {}
    for chunk in RrdReader(str(path)).store().stream():
        entry = out.setdefault(chunk.entity_path, {"frames": set(), "columns": set(), "lengths": {}})
        batch = chunk.to_record_batch()
        entry["columns"].update(batch.schema.names)
        if "frame" in batch.schema.names:
            entry["frames"].update(v for v in batch.column("frame").to_pylist() if v is not None)
        for name in batch.schema.names:
            if ":" in name:
                entry["lengths"].setdefault(name, []).extend(
                    len(v) if isinstance(v, list) else 1 for v in batch.column(name).to_pylist() if v is not None
                )
    return out


def _read_rrd_dataframe(path) -> dict[str, dict]:
    import rerun.dataframe as rd

    recording = rd.load_recording(str(path))
    out: dict[str, dict] = {}
    for col in recording.schema().component_columns():
        entry = out.setdefault(col.entity_path, {"frames": set(), "columns": set(), "lengths": {}})
        name = getattr(col, "component", None) or getattr(col, "component_name", "")
        entry["columns"].add(str(name))
    for entity, entry in out.items():
        table = recording.view(index="frame", contents=entity).select().read_all()
        entry["frames"].update(v for v in table.column("frame").to_pylist() if v is not None)
    return out

"""`rgbdnav localize --gps` on a real log: a simulated receiver (sigma 3 m, 1 Hz, dropouts) along
the Radish orebro path through a geo anchor; the fixes narrow relocalisation and the run chart
shows localiser, odometry and GPS."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from rgbdnav.cli import app
from sensors.carmen import CarmenSource
from sensors.geo import GeoAnchor, geo_yaml_text
from sensors.gps import SimGpsConfig, simulate_gps, write_gps_txt

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
OREBRO = DATA / "radish" / "orebro-corrected.log.gz"
needs_data = pytest.mark.skipif(not OREBRO.is_file(), reason="../shared/data/radish is absent")
ANCHOR = GeoAnchor(44.98, -93.27, 256.0, 0.0)
SIGMA_M = 3.0  # [m]
runner = CliRunner()


@needs_data
@pytest.mark.slow
def test_localize_uses_gps_fixes_through_the_map_geo_anchor(
    tmp_path: Path, orebro_map: Path
) -> None:
    bundle = tmp_path / "map"  # `rgbdnav map` of the log, copied: a geo anchor is added below
    shutil.copytree(orebro_map / "map", bundle)
    src = CarmenSource(OREBRO)
    stamps = np.array([s.stamp_ns for s in src.scans()], np.int64)
    poses = src.laser_poses()
    gps = simulate_gps(
        stamps, np.column_stack([poses.x, poses.y]), ANCHOR, SimGpsConfig(sigma_m=SIGMA_M), seed=0
    )
    write_gps_txt(tmp_path / "gps.txt", gps)
    args = [
        "localize",
        str(OREBRO),
        "--map",
        str(bundle),
        "--gps",
        str(tmp_path / "gps.txt"),
        "--out",
        str(tmp_path / "loc"),
        "-q",
    ]
    # Without a geo anchor the fixes cannot be placed: a one-line error naming the fix.
    refused = runner.invoke(app, args)
    assert refused.exit_code == 1 and "has no geo anchor: add" in refused.output
    (bundle / "geo.yaml").write_text(geo_yaml_text(ANCHOR))
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    summary = json.loads((tmp_path / "loc" / "summary.json").read_text())
    assert summary["gps"]["fixes"] == len(gps)
    assert summary["gps"]["scans_to_first_pose"] is not None
    assert summary["counts"]["tracking"] > 0.9 * summary["counts"]["scans"]
    # The localiser's poses lie within a few sigma of the latest fix (which may be seconds old).
    assert summary["gps"]["gps_vs_localiser"]["median_m"] < 3 * SIGMA_M
    assert (tmp_path / "loc" / "gps.png").stat().st_size > 10_000

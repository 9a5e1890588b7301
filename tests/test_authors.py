"""The authors' Figure 3 data: reading their CSVs and finding their contacts."""

from __future__ import annotations

import os
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from hmpc_cli.analysis.authors import (
    BallGeometry, circle_entry, contacts, end_distance, read_authors, read_panels)

ROOT = Path(__file__).resolve().parents[1]
#: the authors' data as the repository holds it (where hmpc report looks for it)
AUTHORS = Path(os.environ.get("HMPC_AUTHORS_DATA", ROOT / "results" / "authors"))


def _guards(cs) -> list[str]:
    return [c.guard for c in cs]


def _drop(t: np.ndarray, y0: float = 1.0, r: float = 0.1, g: float = 9.81) -> np.ndarray:
    """Height (K,) of a ball dropped at rest from y0 at t = 0, bouncing elastically at r."""
    t_hit = np.sqrt(2 * (y0 - r) / g)
    s = np.where(t < t_hit, t + t_hit, (t - t_hit) % (2 * t_hit))  # since the last bounce
    return r + g * t_hit * s - 0.5 * g * s**2


def test_contacts_of_a_synthetic_bounce_and_crossing():
    t = np.linspace(0.0, 3.0, 400)
    y = _drop(t)
    xy = np.column_stack([np.full_like(t, 5.0), y])
    found = contacts(t, xy)
    t_hit = np.sqrt(2 * 0.9 / 9.81)  # 0.428 s, then every 0.857 s
    assert _guards(found) == ["floor"] * 3  # the 4th falls at 2.999 s, on the last sample
    # extrapolated from the two samples before each minimum (7.5 ms apart): 1.1-1.3e-4 s
    # early of the exact bounce, and the detector is deterministic to the last digits
    assert [c.t for c in found] == pytest.approx(t_hit + np.arange(3) * 2 * t_hit, abs=1.5e-4)
    assert [c.t for c in found] == pytest.approx(
        [0.42848256271723173, 1.2851769599900165, 2.14187183789482], abs=1e-12)
    # a smooth minimum (10 m/s^2 of curvature) above the floor is no contact
    smooth = np.column_stack([np.full_like(t, 5.0), 0.2 + 5.0 * (t - 1.5) ** 2])
    assert contacts(t, smooth) == []
    # into the circle and out again: two crossings, interpolated in time
    line = np.column_stack([np.linspace(1.5, 4.5, 400), np.full(400, 3.0)])
    cross = contacts(t, line)
    assert _guards(cross) == ["circle_in", "circle_out"]
    assert [c.t for c in cross] == pytest.approx([0.5, 2.5], abs=1e-9)
    assert circle_entry(t, line) == pytest.approx(t[t >= 0.5][0])
    # a bounce outside the floor's activity region is no floor contact
    assert contacts(t, xy, BallGeometry(floor_extent=(0.0, 4.0))) == []


def test_the_authors_contacts_as_counted_by_hand():
    panels = read_panels(AUTHORS)
    assert list(panels) == ["10 Hz fixed", "20 Hz fixed", "10 Hz replan", "100 Hz fixed"]
    left = panels["10 Hz fixed"]
    assert list(left) == [f"trial {i}" for i in range(1, 11)] + ["nominal"]
    nominal = contacts(left["nominal"].t, left["nominal"].xy)
    # the reference's six-contact plan (reference README), flown undisturbed
    assert _guards(nominal) == ["floor", "wall", "floor", "floor", "wall", "floor", "circle_in"]
    assert [c.t for c in nominal[:6]] == pytest.approx(
        [0.241, 0.338, 0.677, 1.248, 1.406, 2.000], abs=0.005)
    assert circle_entry(left["nominal"].t, left["nominal"].xy) == pytest.approx(2.180, abs=0.01)
    # the paper's two failures, stuck bouncing in the corner (counted on plots of y(t), x(t))
    for trial, floor, wall in (("trial 5", 15, 4), ("trial 7", 12, 4)):
        cs = contacts(left[trial].t, left[trial].xy)
        assert Counter(_guards(cs)) == {"floor": floor, "wall": wall}
        assert circle_entry(left[trial].t, left[trial].xy) is None
    hz100 = panels["100 Hz fixed"]["trial 5"]
    assert _guards(contacts(hz100.t, hz100.xy)) == [
        "floor", "wall", "floor", "wall", "circle_in", "circle_out", "floor"]
    replan = panels["10 Hz replan"]["trial 6"]
    assert _guards(contacts(replan.t, replan.xy)) == [
        "floor", "wall", "floor", "circle_in", "circle_out", "wall", "floor", "circle_in"]


def test_the_authors_counts_follow_from_their_end_points():
    stable = {panel: sorted(k for k, tr in trials.items() if end_distance(tr.xy) <= 1.0)
              for panel, trials in read_panels(AUTHORS).items()}
    assert {p: len(v) for p, v in stable.items()} == {
        "10 Hz fixed": 9, "20 Hz fixed": 11, "10 Hz replan": 11, "100 Hz fixed": 4}
    assert stable["100 Hz fixed"] == ["nominal", "trial 1", "trial 2", "trial 8"]


def test_bad_authors_files_are_one_line_errors(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,a_x\n0,1\n")
    with pytest.raises(ValueError, match="no 't' column"):
        read_authors(bad)
    bad.write_text("t,a_x,a_y\n0,1,1\n0,1,1\n1,2,2\n")
    with pytest.raises(ValueError, match="not increasing"):
        read_authors(bad)
    bad.write_text("t,a_x\n0,1\n1,1\n2,1\n")
    with pytest.raises(ValueError, match="a lacks its _x or _y column"):
        read_authors(bad)
    with pytest.raises(ValueError, match="cannot read"):
        read_authors(tmp_path / "missing.csv")
    good = tmp_path / "good.csv"
    good.write_text("t,trial1_x,trial1_y,nominal_x,nominal_y\n0,1,1,1,1\n1,2,2,3,3\n2,3,3,3,3\n")
    data = read_authors(good)
    assert list(data) == ["trial 1", "nominal"] and data["nominal"].xy.shape == (3, 2)

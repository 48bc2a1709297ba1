"""``openconvoy report`` warns (one line) when no vehicle moved: a convoy left armed in
MANUAL has perfect-looking metrics (issue 9: p95 0.004 m for a convoy that never drove)."""

from __future__ import annotations

from pathlib import Path

from openconvoy.cli import main
from tests.firmware_runs import unpack


def _standstill_copy(src: Path, dst: Path) -> Path:
    """The real firmware deploy logs, each cut before its vehicle first moved (the armed
    wait), as a run whose convoy never drove would look."""
    dst.mkdir()
    for csv in src.glob("vehicle_*.csv"):
        lines = csv.read_text().splitlines()
        col = lines[0].split(",").index("speed_mps")
        kept = [lines[0]]
        for ln in lines[1:]:
            if abs(float(ln.split(",")[col])) >= 0.02:
                break
            kept.append(ln)
        assert len(kept) > 1, csv
        (dst / csv.name).write_text("\n".join(kept) + "\n")
    return dst


def test_report_warns_when_no_vehicle_moved(tmp_path, capsys):
    still = _standstill_copy(unpack("vx-fixed-1", tmp_path), tmp_path / "still")
    assert main(["report", str(still), "--out", str(tmp_path / "m.json")]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    warnings = [ln for ln in err if ln.startswith("warning: no vehicle moved")]
    assert len(warnings) == 1, err


def test_report_does_not_warn_for_a_convoy_that_drove(tmp_path, capsys):
    run = unpack("vx-fixed-1", tmp_path)
    assert main(["report", str(run), "--out", str(tmp_path / "m.json")]) == 0
    assert "no vehicle moved" not in capsys.readouterr().err

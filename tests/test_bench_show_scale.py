"""``scripts/bench_show_scale.py`` at a tiny scale: four projectors in a 2×2 grid (the row of four is the same code
with the side-by-side layout; left out to keep this under half a minute), each one's operator built in a process of
its own, the joint solve timed against one projector's, the table printed, and a second run reusing every figure
kept in ``--work``."""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_show_scale", REPO / "scripts" / "bench_show_scale.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_show_scale_bench_runs_small_and_reuses_its_work(tmp_path, capsys):
    bench = _bench()
    argv = ["--work", str(tmp_path), "--layouts", "2x2", "--scale", "0.1", "--camera-size", "1280x960", "--spp", "1",
            "--repeat", "1", "--targets", "city"]
    text = bench.main(argv)
    out = capsys.readouterr().out
    assert "building projector 4's operator" in out and "timing the joint solve" in out
    assert "Camera 128×96, 4 projectors with 192×108 inputs" in text and "the lab's truth" in text
    rows = [line.split("|") for line in text.splitlines() if line.startswith("| 2x2 |")]
    assert len(rows) == 4 + 1 + 1  # four operators, one target, the summary
    assert [r[2].strip() for r in rows[:4]] == ["1", "2", "3", "4"]
    assert rows[5][3].strip() == "4.00×"  # four operators of one size against one
    joint, alone = (float(v) for v in rows[5][6].split("/"))
    assert joint > alone > 0
    ratio, cpu = rows[5][7].split("×", 1)
    assert abs(float(ratio) - joint / alone) < 0.05 * joint / alone and cpu.strip().startswith("(")
    assert rows[4][5].strip() in {"1", "2", "3", "4"}  # the projector timed alone
    assert (tmp_path / "table.md").read_text().strip() == text.strip()
    t0 = time.perf_counter()
    again = bench.main(argv)  # everything kept: nothing built or timed again
    assert again == text and "building" not in capsys.readouterr().out
    assert time.perf_counter() - t0 < 5

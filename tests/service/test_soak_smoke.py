"""bench/soak.py, compressed to a smoke run: the service at the reference load, a clean phase
then hostile frames; it runs, judges outputs in both phases, pings the watchdog, writes its
record, and sees no published value beyond its uncertainty without a flag (exit 0)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_soak_smoke_run(tmp_path) -> None:
    out = tmp_path / "soak_smoke.json"
    # 16 s of the paper cycle's 24.6 s lap. Clean (8 s, the warm-up too): judged from 1 s
    # after the boom's first reference (4.4 s), while it rises. Hostile: the boom ends its
    # rise, the bucket rises and lowers again. A state save every 5 s.
    proc = subprocess.run([sys.executable, str(REPO / "bench" / "soak.py"), "--duration-s",
                           "16", "--clean-s", "8", "--flood-hz", "500", "--out", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=REPO, check=False)
    assert "Traceback" not in proc.stderr + proc.stdout, proc.stderr[-3000:]
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    figures = json.loads(out.read_text())["figures"]
    assert figures["violations"] == 0
    assert figures["phases"]["clean"]["judged"] > 0 and figures["phases"]["hostile"]["judged"] > 0
    assert figures["watchdog_pings"] > 0 and figures["state_saves"] > 0
    for key in ("rss_growth_mb_per_h_after_warmup", "watchdog_largest_gap_s",
                "flagged_share_difference_points"):
        assert key in figures

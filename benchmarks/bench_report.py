"""The HTML report (`--report`, issue 22): its size, the time to write it and the time headless
Chromium takes to draw it, on the real scans and on a 10 M-point synthetic city.

Cases (each one ``sdp ... --report`` subprocess with ``--json``, then 3 visits in headless
Chromium through tests/browser.py, a fresh browser each; `make browser` installs it):

- Toronto ALS 2015 → 2023 (``sdp change`` and ``sdp distance``, aligned on the ground class);
- mOSD learn0 → learn1 (``sdp change``, the files' sensor);
- a 10 M-point city (``../shared/tools/city_epochs.py 1e7 DIR``: two LAZ epochs of 10 M points;
  cached in ``$SDP_BENCH_DATA`` or /tmp/sdp-bench-report) compared in memory at ``--voxel-size 1``
  (at 0.25 the dense-grid estimate exceeds the 4 GiB limit and the comparison goes to tiles,
  which make no report).

Reported per case: points, report size, report time (the step alone, from the summary),
whole command, the median of the visits (from the request until plotly has drawn), console
errors, the load average.

    python benchmarks/bench_report.py            # writes benchmarks/results/report.md
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import browser  # noqa: E402

DATA = ROOT.parent / "shared" / "data"
TOOL = ROOT.parent / "shared" / "tools" / "city_epochs.py"
CACHE = Path(os.environ.get("SDP_BENCH_DATA", "/tmp/sdp-bench-report"))


def city() -> tuple[Path, Path]:
    a, b = CACHE / "epoch1.laz", CACHE / "epoch2.laz"
    if not (a.exists() and b.exists()):
        CACHE.mkdir(parents=True, exist_ok=True)
        subprocess.run([sys.executable, str(TOOL), "1e7", str(CACHE)], check=True)
    return a, b


def cases(out: Path):
    tor = (DATA / "als_toronto" / "TTP_2015.laz", DATA / "als_toronto" / "TTP_2023.laz")
    align = ["--align", "density", "--align-class", "2", "--fix-horizontal"]
    yield "Toronto ALS, change", ["change", *tor, "-o", out / "tor.laz", "--both", *align]
    yield "Toronto ALS, distance", ["distance", *tor, "-o", out / "tord.laz", *align]
    mosd = (DATA / "mosd" / "learn" / "learn0.pcd", DATA / "mosd" / "learn" / "learn1.pcd")
    yield "mOSD learn0 → learn1, change", ["change", *mosd, "-o", out / "mosd.ply", "--both"]
    yield "city 10 M + 10 M points, change", ["change", *city(), "-o", out / "city.laz", "--voxel-size", "1",
                                              "--memory-limit", "8GB"]


def main() -> None:
    why = browser.missing()
    if why:
        sys.exit(f"no headless browser: {why}")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        for i, (name, args) in enumerate(cases(out)):
            report = out / f"report{i}.html"
            t = time.perf_counter()
            p = subprocess.run([str(ROOT / ".venv" / "bin" / "sdp"), *map(str, args), "--report", str(report),
                                "--json"], capture_output=True, text=True, check=True)
            wall = time.perf_counter() - t
            s = json.loads(p.stdout)
            points = s["current"]["points"] + s["reference"]["points"] if "current" in s else s["core_points"]
            visits = [browser.visit(report) for _ in range(3)]
            errors = sorted({e for v in visits for e in v.errors})
            load = os.getloadavg()[0]
            rows.append((name, points, report.stat().st_size / 1e6, s["timings"]["report"], wall,
                         statistics.median(v.seconds for v in visits), max(v.seconds for v in visits),
                         all(v.rendered for v in visits), errors, load))
            print(rows[-1], flush=True)
    lines = ["# HTML reports (`benchmarks/bench_report.py`)", "",
             f"{time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores; headless Chromium "
             "(Debian's, SwiftShader WebGL) through Selenium, 3 visits each, a fresh browser per visit.", "",
             "| case | points | report | writing it | whole command | drawn in Chromium (median, max) | "
             "console errors | load |", "|---|---:|---:|---:|---:|---:|---|---:|"]
    for name, n, mb, rep, wall, med, worst, drawn, errors, load in rows:
        lines.append(f"| {name} | {n:,} | {mb:.1f} MB | {rep:.1f} s | {wall:.1f} s | {med:.1f} s, {worst:.1f} s"
                     f"{'' if drawn else ' (not drawn)'} | {len(errors) or 'none'} | {load:.1f} |")
    (ROOT / "benchmarks" / "results" / "report.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()

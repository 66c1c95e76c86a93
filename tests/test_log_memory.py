"""Memory of `cfknode plot` on long flights: a 600 s flight must plot in under 300 MB peak RSS.

Writing a 600 s log takes half a minute, so the bound is checked by extrapolation: peak RSS of
plotting a 6 s and a 60 s synthetic log (same channels and rates as a flight), each in a fresh
process, gives the cost per flight second; 600 s = the 60 s peak + 540 s at that cost.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np

from cfknode.app.ui.plotting import read_for_plot
from synthetic_log import write_synthetic_flight

BOUND_MB = 300.0
# Peak RSS of the child itself: VmHWM belongs to the process's own memory map, while
# getrusage's ru_maxrss survives exec and would report pytest's own peak at the fork.
PLOT_AND_MEASURE = """
import resource, sys
from cfknode.app.cli import main
code = main(["plot", sys.argv[1], "--out", sys.argv[2]])
try:
    with open("/proc/self/status") as f:
        kib = next(int(line.split()[1]) for line in f if line.startswith("VmHWM:"))
except OSError:
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
print(code, kib)
"""


def peak_rss_mb(log: Path, out: Path) -> float:
    proc = subprocess.run([sys.executable, "-c", PLOT_AND_MEASURE, str(log), str(out)],
                          capture_output=True, text=True, timeout=300)
    code, kib = proc.stdout.split()[-2:]
    assert proc.returncode == 0 and code == "0", proc.stderr
    return int(kib) / 1024


def test_a_600_s_flight_plots_in_under_300_mb(tmp_path):
    short = write_synthetic_flight(tmp_path / "short", 6.0)
    long = write_synthetic_flight(tmp_path / "long", 60.0)
    rss_short, rss_long = peak_rss_mb(short, tmp_path / "p6"), peak_rss_mb(long, tmp_path / "p60")
    per_second = max(rss_long - rss_short, 0.0) / 54.0
    predicted = rss_long + 540.0 * per_second
    print(f"peak RSS: 6 s {rss_short:.0f} MB, 60 s {rss_long:.0f} MB -> 600 s about {predicted:.0f} MB")
    assert predicted < BOUND_MB


def test_the_plot_reader_keeps_float_arrays_not_messages(tmp_path):
    log = read_for_plot(write_synthetic_flight(tmp_path, 2.0))
    p = log.array("/state", "p_true")
    assert p.dtype == np.float64 and p.shape == (800, 3)
    assert log.times("/reference").shape == (800,) and log.array("/tick", "solve_s").dtype == np.float64
    # Per message it keeps 8 bytes per plotted number (p, p_true, reference p, two tick times, and t).
    kept = sum(len(col.values) * col.values.itemsize for cols in log.sink.columns.values() for col in cols.values())
    kept += sum(len(t) * t.itemsize for t in log.sink.times.values())
    assert kept == 800 * 8 * (3 + 3 + 3 + 2 + 3)

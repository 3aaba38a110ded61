"""The benchmark script, in its quick mode: it runs end to end and writes every table.
Its numbers are timings, for reading only; nothing here asserts a time."""
import re
import subprocess
import sys
from pathlib import Path

SCRIPT = Path(__file__).resolve().parent.parent / "scripts" / "bench.py"


def test_quick_benchmark_writes_every_table(tmp_path):
    done = subprocess.run([sys.executable, str(SCRIPT), "--quick"], cwd=tmp_path, capture_output=True, text=True,
                          timeout=900)
    assert done.returncode == 0, done.stderr[-2000:]
    text = (tmp_path / "bench_quick.md").read_text()
    assert "Fig. 6(c)-class solve" in text and "| refinement |" in text
    assert "Where the time goes" in text and "| function | calls |" in text
    computing, views = (int(n.replace(",", "")) for n in
                        re.search(r"Torch operators per shot .*?: ([\d,]+) that compute, ([\d,]+) views", text).groups())
    assert computing > 0 and views > 0
    scaling = re.findall(r"^\| (\d+) \| [\d.]+ \|", text, flags=re.MULTILINE)
    assert len(scaling) == 2 and int(scaling[0]) < int(scaling[1])  # the 1k and 10k rows
    converged = re.findall(r"^\| floating \| (paper|default) \| \d+ \| [-\d]+ \| (\d+) \((\d+)\)", text, flags=re.MULTILINE)
    assert [c[0] for c in converged] == ["paper", "default"]
    (_, paper_shots, paper_renders), (_, shots, renders) = converged
    assert int(shots) < int(paper_shots) and int(renders) < int(paper_renders)  # patches: fewer of both

"""The README's Python example runs as written in a fresh interpreter: importing cpgjax prints nothing on stdout,
and the example prints J, v_x and CoT for each friction (the printed values checked against the trial's own
definitions: CoT > 0, J finite, v_x a walking speed), the very figures the matching `cpgjax walk` prints (one default
physics profile for both, docs/decisions.md §15)."""

import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_importing_cpgjax_prints_nothing():
    code = "import cpgjax, cpgjax.cli, cpgjax.mjx_go1, cpgjax.ablation, cpgjax.sim.backends, cpgjax.deployment.deploy"
    done = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=300,
        env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout == ""


def _walk_rows(stdout: str) -> dict[str, tuple[str, str, str]]:
    """friction → (J, v_x, CoT) as `cpgjax walk` prints them (its trials table)."""
    head = next(line for line in stdout.splitlines() if line.startswith("| walk |"))
    names = [c.strip() for c in head.strip("|").split("|")]
    rows = {}
    for line in stdout.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| ") and cells[0].isdigit():
            row = dict(zip(names, cells, strict=True))
            j = next(v for k, v in row.items() if k.startswith("J "))
            rows[row["friction"]] = (j, row["v_x [m/s]"], row["CoT"])
    return rows


def test_the_readme_python_example_prints_j_velocity_and_cot(tmp_path):
    readme = (ROOT / "README.md").read_text()
    example = next(block for block in re.findall(r"```python\n(.*?)```", readme, re.S) if "make_backend" in block)
    done = subprocess.run(
        [sys.executable, "-c", example],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
        env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)},
    )
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert len(lines) == 3, done.stdout
    for line, friction in zip(lines, ("0.3", "0.6", "0.9"), strict=True):
        m = re.fullmatch(rf"friction {friction}: J (\S+), v_x (\S+) m/s, CoT (\S+)", line)
        assert m, line
        j, v, cot = map(float, m.groups())
        assert 0.0 < cot < 5.0 and 0.05 < v < 1.5 and -10.0 < j < 10.0
    walked = subprocess.run(
        [
            sys.executable,
            "-m",
            "cpgjax.cli",
            "walk",
            "--controllers",
            "vmc_tegotae",
            "--friction",
            "0.3,0.6,0.9",
            "--trials",
            "1",
        ],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=600,
        env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)},
    )
    assert walked.returncode == 0, walked.stderr[-2000:]
    rows = _walk_rows(walked.stdout)
    for line, friction in zip(lines, ("0.3", "0.6", "0.9"), strict=True):
        j, v, cot = re.fullmatch(r"friction \S+: J (\S+), v_x (\S+) m/s, CoT (\S+)", line).groups()
        assert rows[friction] == (j, v, cot), (friction, line, walked.stdout)

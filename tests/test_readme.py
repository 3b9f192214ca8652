"""The README's Python example runs as written in a fresh interpreter: importing cpgjax prints nothing on stdout,
and the example prints J, v_x and CoT for each friction (the printed values checked against the trial's own
definitions: CoT > 0, J finite, v_x a walking speed)."""

import os
import pathlib
import re
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parent.parent


def test_importing_cpgjax_prints_nothing():
    code = "import cpgjax, cpgjax.cli, cpgjax.mjx_go1, cpgjax.ablation, cpgjax.sim.backends, cpgjax.deployment.deploy"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=300,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout == ""


def test_the_readme_python_example_prints_j_velocity_and_cot(tmp_path):
    readme = (ROOT / "README.md").read_text()
    example = next(block for block in re.findall(r"```python\n(.*?)```", readme, re.S) if "make_backend" in block)
    done = subprocess.run([sys.executable, "-c", example], capture_output=True, text=True, cwd=tmp_path, timeout=600,
                          env={**os.environ, "JAX_PLATFORMS": "cpu", "PYTHONPATH": str(ROOT)})
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    assert len(lines) == 3, done.stdout
    for line, friction in zip(lines, ("0.3", "0.6", "0.9"), strict=True):
        m = re.fullmatch(rf"friction {friction}: J (\S+), v_x (\S+) m/s, CoT (\S+)", line)
        assert m, line
        j, v, cot = map(float, m.groups())
        assert 0.0 < cot < 5.0 and 0.05 < v < 1.5 and -10.0 < j < 10.0

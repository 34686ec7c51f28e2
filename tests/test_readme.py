"""The README's example runs and does what it says."""

import pathlib
import re

import numpy as np
import pytest

import ceemx


@pytest.mark.slow  # the README example's fit (≈ 6 s; tests/test_docs.py keeps its text)
def test_readme_example_runs():
    text = (pathlib.Path(__file__).parents[1] / "README.md").read_text()
    code = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    namespace: dict = {}
    # The example's data are simulated without process noise, below the model's assumed noise:
    # the end-of-fit noise check says so.
    with pytest.warns(ceemx.NoiseCheckWarning, match="too loose"):
        exec(compile(code, "README.md", "exec"), namespace)
    result, true = namespace["result"], namespace["true"]
    assert result.converged
    np.testing.assert_allclose(result.system.sigma, true.sigma, rtol=1e-2)
    np.testing.assert_allclose(result.system.rho, true.rho, rtol=1e-2)

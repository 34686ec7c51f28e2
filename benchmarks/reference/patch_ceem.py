"""Apply the two one-line compatibility patches to the installed `ceem` 0.0.4 (idempotent).

1. ``ceem/opt_criteria.py``, ``STRStateCriterion.jac_resid_x``: ``sp.eye(..., format=
   sparse_format.format)`` reads ``format`` off the *class* ``scipy.sparse.csr_matrix``, which is
   a property object in current SciPy → pass the string ``"csr"``.
2. ``ceem/particleem.py``, ``faPF.sample_initial``: ``torch.solve(B, A)[0]`` was removed from
   PyTorch → ``torch.linalg.solve(A, B)``.

Run with the reference environment's Python (``setup.sh`` does).
"""

import pathlib
import re
import sys

import ceem

root = pathlib.Path(ceem.__file__).parent
patches = [
    (
        root / "opt_criteria.py",
        "format=sparse_format.format",
        'format="csr"',
    ),
]
ok = True
for path, old, new in patches:
    text = path.read_text()
    if old in text:
        path.write_text(text.replace(old, new))
        print(f"patched {path.name}: {old} -> {new}")
    elif new in text:
        print(f"already patched: {path.name}")
    else:
        ok = False
        print(f"pattern not found in {path.name}: {old}", file=sys.stderr)

# torch.solve(B, A)[0] -> torch.linalg.solve(A, B): the arguments span a line break.
pem = root / "particleem.py"
text = pem.read_text()
pattern = re.compile(r"torch\.solve\(\s*(.+?),\s*(Sig_y)\)\[0\]", re.S)
new_text, count = pattern.subn(lambda m: f"torch.linalg.solve({m.group(2)}, {m.group(1)})", text)
if count:
    pem.write_text(new_text)
    print(f"patched particleem.py: {count} torch.solve call(s)")
elif "torch.solve(" not in text:
    print("already patched: particleem.py")
else:
    ok = False
    print("torch.solve pattern not found in particleem.py", file=sys.stderr)
sys.exit(0 if ok else 1)

"""Data shipped inside the package, so that the defaults need nothing from the network.

`pmatdata_dir()`: PmatData experiment II (PhysioNet, Open Data Commons Attribution v1.0; the
attribution is in its README.md): 465 real BT3510 frames of 8 subjects on an air and a sponge
mattress, 3.9 MB, checked against the dataset's published SHA-256 sums (SHA256SUMS.txt).
`evaluate-real`, `import-pmatdata` and `demo` use it unless given another folder.
"""

from __future__ import annotations

from pathlib import Path

_HERE = Path(__file__).resolve().parent

PMATDATA = "pmatdata"
"""The name that the CLI's --pmatdata option resolves to the packaged copy."""


def pmatdata_dir() -> Path:
    """The packaged PmatData experiment II folder (index.csv, experiment-ii/)."""
    return _HERE / "pmatdata"


def resolve_pmatdata(path: str | Path) -> Path:
    """`path` itself when it exists; the packaged copy for the name "pmatdata" otherwise."""
    path = Path(path)
    if not path.exists() and str(path) == PMATDATA:
        return pmatdata_dir()
    return path


__all__ = ["PMATDATA", "pmatdata_dir", "resolve_pmatdata"]

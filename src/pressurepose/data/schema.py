"""One dataset sample's fields, their units, and their Parquet (Arrow) layout.

A shard is a Parquet table with one row per sample. Images and vectors are stored as
fixed-size lists, flattened in C order (a 64 x 27 image is 1,728 values, row 0 at the head
end), so any Parquet reader (pandas, DuckDB, Ray Data, HF datasets) can open a shard; the
column metadata carries each field's shape and unit. Meshes are not stored: they follow from
the body parameters through the body model (`model(params)`), which also reproduces the
stored joints.
"""

from __future__ import annotations

import dataclasses

import numpy as np

ROWS, COLS = 64, 27  # BT3510 taxels: rows along the bed (row 0 at the head end), columns across
NUM_JOINTS = 24  # J24 (SMPL's joint names and order)
NUM_POSE_JOINTS = 23


@dataclasses.dataclass(frozen=True)
class Field:
    name: str
    shape: tuple[int, ...]  # per sample; () for a scalar; -1 = set by the body model (shape)
    dtype: str  # numpy dtype name, or "str"
    unit: str
    doc: str


FIELDS: tuple[Field, ...] = (
    Field("split", (), "str", "", "train or test"),
    Field("partition", (), "str", "", "seed Table 4 partition (sampling.partitions.PARTITIONS)"),
    Field("gender", (), "str", "", "female or male"),
    Field("over_bed", (), "bool", "", "limbs sampled over the mattress (seed A.7)"),
    Field(
        "index",
        (),
        "int64",
        "",
        "sampler index: the initial pose is PoseSampler(seed, partition, gender, over_bed).sample([index])",
    ),
    Field("pressure_mmhg", (ROWS, COLS), "float32", "mmHg", "simulated BT3510 reading, clipped to [0, 100]"),
    Field("depth_mm", (ROWS, COLS), "float32", "mm", "depth map Q of the body's underside (PMR target)"),
    Field("contact", (ROWS, COLS), "uint8", "", "contact map C (1 where the body touches the mattress)"),
    Field("shape", (-1,), "float64", "", "body-model shape parameters (Anny phenotypes or SMPL betas)"),
    Field("root_rotation", (3,), "float64", "rad", "root axis-angle, mat frame"),
    Field("root_translation", (3,), "float64", "m", "pelvis position, mat frame"),
    Field("pose", (NUM_POSE_JOINTS, 3), "float64", "rad", "23 joint rotations, axis-angle, J24 tree"),
    Field("joints_m", (NUM_JOINTS, 3), "float64", "m", "J24 joints at rest, mat frame"),
    Field("mass_kg", (), "float64", "kg", "body mass (mesh volume x 980 kg/m^3)"),
    Field("height_m", (), "float64", "m", "standing height of the shape"),
    Field("head_angle_deg", (), "float64", "deg", "head section of the bed raised by this angle (0 = flat)"),
    Field(
        "settle_steps",
        (),
        "int32",
        "",
        "sim #1 steps until the body settled; the articulated rest: its re-posings, or ArticulatedConfig.outer + 1"
        " for a body still moving when they ran out",
    ),
    Field("sink_mm", (), "float32", "mm", "sim #2 deepest mattress compression"),
)
FIELD_BY_NAME = {f.name: f for f in FIELDS}
NAMES = tuple(f.name for f in FIELDS)


@dataclasses.dataclass(frozen=True)
class SampleBatch:
    """B samples as numpy arrays, one attribute per schema field (shapes in FIELDS, leading B)."""

    split: np.ndarray
    partition: np.ndarray
    gender: np.ndarray
    over_bed: np.ndarray
    index: np.ndarray
    pressure_mmhg: np.ndarray
    depth_mm: np.ndarray
    contact: np.ndarray
    shape: np.ndarray
    root_rotation: np.ndarray
    root_translation: np.ndarray
    pose: np.ndarray
    joints_m: np.ndarray
    mass_kg: np.ndarray
    height_m: np.ndarray
    head_angle_deg: np.ndarray
    settle_steps: np.ndarray
    sink_mm: np.ndarray

    def __post_init__(self) -> None:
        B = len(self.index)
        shape_dim = self.shape.shape[1] if self.shape.ndim == 2 else -1
        for f in FIELDS:
            value = getattr(self, f.name)
            want = (B, *(shape_dim if s == -1 else s for s in f.shape))
            if value.shape != want:
                raise ValueError(f"SampleBatch.{f.name} must have shape {want}, got {value.shape}")
            if f.dtype not in ("str", "bool") and value.dtype.kind == "f" and not np.isfinite(value).all():
                raise ValueError(f"SampleBatch.{f.name} holds NaN or infinite values")

    def __len__(self) -> int:
        return int(len(self.index))

    @staticmethod
    def concat(batches: list[SampleBatch]) -> SampleBatch:
        if not batches:
            raise ValueError("nothing to concatenate")
        return SampleBatch(**{n: np.concatenate([getattr(b, n) for b in batches]) for n in NAMES})

    def take(self, rows) -> SampleBatch:
        rows = np.asarray(rows, dtype=np.int64)
        return SampleBatch(**{n: getattr(self, n)[rows] for n in NAMES})


def arrow_schema(shape_dim: int):
    """The Arrow schema of a shard for a body model with `shape_dim` shape parameters."""
    import pyarrow as pa

    fields = []
    for f in FIELDS:
        base = pa.string() if f.dtype == "str" else pa.from_numpy_dtype(np.dtype(f.dtype))
        size = int(np.prod([shape_dim if s == -1 else s for s in f.shape])) if f.shape else 0
        typ = pa.list_(base, size) if f.shape else base
        meta = {"shape": ",".join(str(shape_dim if s == -1 else s) for s in f.shape), "unit": f.unit, "doc": f.doc}
        fields.append(pa.field(f.name, typ, nullable=False, metadata=meta))
    return pa.schema(fields, metadata={"format": "pressurepose-shard", "format_version": "1"})


def to_table(batch: SampleBatch):
    """SampleBatch -> pyarrow.Table (fixed-size lists for arrays)."""
    import pyarrow as pa

    schema = arrow_schema(batch.shape.shape[1])
    columns = []
    for f, _field in zip(FIELDS, schema):
        value = getattr(batch, f.name)
        if f.dtype == "str":
            columns.append(pa.array([str(v) for v in value], pa.string()))
        elif f.shape:
            flat = np.ascontiguousarray(value, dtype=f.dtype).reshape(len(batch), -1)
            columns.append(pa.FixedSizeListArray.from_arrays(pa.array(flat.reshape(-1)), flat.shape[1]))
        else:
            columns.append(pa.array(np.asarray(value, dtype=f.dtype)))
    return pa.Table.from_arrays(columns, schema=schema)


def from_table(table, columns: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """pyarrow.Table (or RecordBatch) -> {field: (B, *shape) numpy array} for `columns` (all)."""
    out = {}
    names = columns or tuple(n for n in NAMES if n in table.schema.names)
    for name in names:
        f = FIELD_BY_NAME.get(name)
        if f is None:
            raise ValueError(f"unknown column {name!r}; columns: {', '.join(NAMES)}")
        col = table.column(name)
        if f.dtype == "str":
            out[name] = np.array(col.to_pylist(), dtype=object)
        elif f.shape:
            flat = col.combine_chunks() if hasattr(col, "combine_chunks") else col
            values = flat.flatten().to_numpy(zero_copy_only=False)
            B = len(flat)
            shape = tuple(s if s != -1 else -1 for s in f.shape)
            out[name] = values.astype(f.dtype, copy=False).reshape(B, *shape)
        else:
            out[name] = col.to_numpy(zero_copy_only=False).astype(f.dtype, copy=False)
    return out


__all__ = ["COLS", "FIELDS", "NAMES", "ROWS", "Field", "SampleBatch", "arrow_schema", "from_table", "to_table"]

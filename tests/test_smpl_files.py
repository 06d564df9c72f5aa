"""SMPL model files: generated fixture, restricted unpickler, clear errors."""

import pickle
import sys
import types

import numpy as np
import pytest
import torch

from pressurepose.body import BodyParams, load_body_model
from pressurepose.body.smpl_backend import SmplFileError, read_smpl_file


def _arrays(smpl_dir):
    with np.load(smpl_dir / "SMPL_NEUTRAL.npz") as data:
        return {k: data[k] for k in data.files}


def test_official_style_pickle_with_chumpy_and_sparse_objects(smpl_dir, tmp_path, monkeypatch):
    """An official-style .pkl (chumpy arrays, a scipy sparse regressor) loads without chumpy
    or scipy, and gives the same model as the .npz."""
    arrays = _arrays(smpl_dir)

    class Ch:  # what chumpy pickles: an object whose state holds the array under 'x'
        def __init__(self, x):
            self.x = x

    class csc_matrix:  # what scipy pickles for a CSC matrix
        def __init__(self, dense):
            cols = [np.flatnonzero(dense[:, k]) for k in range(dense.shape[1])]
            self.indices = np.concatenate(cols)
            self.indptr = np.r_[0, np.cumsum([len(c) for c in cols])]
            self.data = np.concatenate([dense[c, k] for k, c in enumerate(cols)])
            self._shape = dense.shape
            self.format = "csc"

    for name in ("chumpy", "scipy", "scipy.sparse"):
        monkeypatch.setitem(sys.modules, name, types.ModuleType(name))
    for name, cls in (("chumpy.ch", Ch), ("scipy.sparse.csc", csc_matrix)):
        module = types.ModuleType(name)
        setattr(module, cls.__name__, cls)
        cls.__module__, cls.__qualname__ = name, cls.__name__
        monkeypatch.setitem(sys.modules, name, module)
    payload = dict(arrays, shapedirs=Ch(arrays["shapedirs"]), J_regressor=csc_matrix(arrays["J_regressor"]))
    folder = tmp_path / "pkl"
    folder.mkdir()
    with open(folder / "SMPL_NEUTRAL.pkl", "wb") as f:
        pickle.dump(payload, f, protocol=2)
    for name in ("chumpy", "chumpy.ch"):
        monkeypatch.delitem(sys.modules, name)  # loading must not need chumpy
    loaded = read_smpl_file(folder / "SMPL_NEUTRAL.pkl")
    assert np.allclose(loaded["J_regressor"], arrays["J_regressor"])
    assert np.allclose(loaded["shapedirs"], arrays["shapedirs"])
    a = load_body_model("smpl", model_dir=folder, dtype=torch.float64)
    b = load_body_model("smpl", model_dir=smpl_dir, dtype=torch.float64)
    p = BodyParams.zeros(1, torch.ones(1, 10, dtype=torch.float64))
    assert torch.allclose(a(p).vertices, b(p).vertices)


class _Evil:
    def __reduce__(self):
        return (print, ("pwned",))


def test_pickle_with_code_is_refused(tmp_path):
    path = tmp_path / "SMPL_NEUTRAL.pkl"
    with open(path, "wb") as f:
        pickle.dump({"v_template": _Evil()}, f)
    with pytest.raises(SmplFileError, match="builtins.print, which is not allowed"):
        read_smpl_file(path)


def test_missing_file_says_where(tmp_path):
    with pytest.raises(SmplFileError, match=r"SMPL_FEMALE.npz or .pkl not found in .*smpl.is.tue.mpg.de"):
        load_body_model("smpl", model_dir=tmp_path, gender="female")


def test_corrupt_truncated_and_malformed_files(smpl_dir, tmp_path):
    (tmp_path / "SMPL_NEUTRAL.npz").write_bytes(b"")
    with pytest.raises(SmplFileError, match="cannot read SMPL model file"):
        read_smpl_file(tmp_path / "SMPL_NEUTRAL.npz")
    good = (smpl_dir / "SMPL_NEUTRAL.npz").read_bytes()
    (tmp_path / "SMPL_NEUTRAL.npz").write_bytes(good[: len(good) // 2])
    with pytest.raises(SmplFileError, match="cannot read SMPL model file"):
        read_smpl_file(tmp_path / "SMPL_NEUTRAL.npz")
    arrays = _arrays(smpl_dir)
    np.savez(tmp_path / "SMPL_MALE.npz", **dict(arrays, weights=arrays["weights"][:, :10]))
    with pytest.raises(SmplFileError, match=r"weights has shape \(6890, 10\), expected \(6890, 24\)"):
        read_smpl_file(tmp_path / "SMPL_MALE.npz")
    del arrays["posedirs"]
    np.savez(tmp_path / "SMPL_FEMALE.npz", **arrays)
    with pytest.raises(SmplFileError, match="lacks posedirs"):
        read_smpl_file(tmp_path / "SMPL_FEMALE.npz")


def test_unknown_gender(smpl_dir):
    with pytest.raises(ValueError, match="unknown SMPL gender 'other'"):
        load_body_model("smpl", model_dir=smpl_dir, gender="other")


def test_sparse_states_rebuild_csc_and_csr():
    from pressurepose.body.smpl_backend import _CsrState, _SparseState

    dense = np.array([[0.0, 2.0, 0.0], [1.0, 0.0, 3.0]])
    csc, csr = _SparseState(), _CsrState()
    csc.__setstate__(
        {
            "data": np.array([1.0, 2.0, 3.0]),
            "indices": np.array([1, 0, 1]),
            "indptr": np.array([0, 1, 2, 3]),
            "_shape": (2, 3),
        }
    )
    csr.__setstate__(
        {
            "data": np.array([2.0, 1.0, 3.0]),
            "indices": np.array([1, 0, 2]),
            "indptr": np.array([0, 1, 3]),
            "_shape": (2, 3),
        }
    )
    assert np.array_equal(csc.to_array(), dense) and np.array_equal(csr.to_array(), dense)

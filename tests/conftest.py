import pytest
import torch

from pressurepose.body import load_body_model
from pressurepose.body.smpl_backend import write_synthetic_smpl_file


@pytest.fixture(scope="session")
def anny64():
    """Anny in float64 (shared: loading takes ~1 s once the cache exists)."""
    return load_body_model("anny", dtype=torch.float64)


@pytest.fixture(scope="session")
def anny32():
    return load_body_model("anny", dtype=torch.float32)


@pytest.fixture
def untrained_run(anny32, tmp_path):
    """A factory: an untrained network of the given NetConfig fields (Anny, float32) saved as a run
    folder under tmp_path; returns (run folder, network)."""
    from pressurepose.net import NetConfig, PressureNet
    from pressurepose.train.checkpoint import save_model

    def make(name: str = "run", **fields):
        net = PressureNet(NetConfig(**fields), body=anny32).eval()
        run = tmp_path / name
        run.mkdir()
        save_model(run, net, {"train": {}, "net": dict(net.config.__dict__)})
        return run, net

    return make


@pytest.fixture(scope="session")
def smpl_dir(tmp_path_factory):
    folder = tmp_path_factory.mktemp("smpl")
    write_synthetic_smpl_file(folder / "SMPL_NEUTRAL.npz")
    return folder


@pytest.fixture(scope="session")
def smpl64(smpl_dir):
    return load_body_model("smpl", model_dir=smpl_dir, dtype=torch.float64)


def pytest_collection_modifyitems(config, items):
    if torch.cuda.is_available():
        return
    skip = pytest.mark.skip(reason="needs a CUDA device")
    for item in items:
        if "gpu" in item.keywords:
            item.add_marker(skip)

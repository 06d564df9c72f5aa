"""`pressurepose view` and `pressurepose click`: the local web pages (`viz.viewer`,
`viz.clicker`), and `pressurepose cache`."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import tyro

from pressurepose.body.anny_backend import load_anny
from pressurepose.cache import cache_dir
from pressurepose.viz import viewer
from pressurepose.viz.clicker import ClickConfig, make_click_server
from pressurepose.viz.viewer import ViewConfig, serve


def view(path: tyro.conf.Positional[Path], port: int = 8765, open: bool = True, data: Path | None = None,
         model: Path | None = None, backend: Literal["anny", "smpl"] | None = None, smpl_dir: Path | None = None) -> None:
    """Browse samples and predictions in a local web page on 127.0.0.1: pressure images, true
    and estimated 3D bodies, joint errors, training curves (docs/viewer.md). Ctrl-C stops it.

    Args:
        path: Dataset folder (manifest.json), `evaluate` report folder, training run folder, or a
            .npz of pressure images (import-pmatdata).
        port: Port on 127.0.0.1 (0: any free port).
        open: Open the page in the default web browser.
        data: Dataset of a report or run, when the path recorded in it is not found.
        model: Training run whose network estimates the bodies shown (datasets, .npz images).
        backend: Body model (default: the dataset's or run's, else anny).
        smpl_dir: Folder with the SMPL files for --backend smpl.
    """
    cfg = ViewConfig(path=path, port=port, open=open, data=data, model=model, backend=backend, smpl_dir=smpl_dir)
    serve(cfg, ready=lambda url: print(f"viewing {path} at {url} (Ctrl-C stops)", flush=True))
    print("viewer stopped")


def click(image: tyro.conf.Positional[Path], out: Path = Path("markers.json"), fx: float | None = None,
          fy: float | None = None, cx: float | None = None, cy: float | None = None, intrinsics: Path | None = None,
          depth_unit: Literal["auto", "m", "mm"] = "auto", port: int = 8765, open: bool = True) -> None:
    """Click the mat's corner markers in a camera image on a local web page (127.0.0.1) and
    save the marker file `coregister --markers` reads (docs/real_data.md). Ctrl-C stops it.

    Args:
        image: RGB image (.png, .jpg) or depth image (.npy, (H, W), metres or millimetres;
            clicks then record the marker's depth).
        out: Marker file to write; an existing one is loaded for editing.
        fx: Focal length along u (pixels).
        fy: Focal length along v (pixels).
        cx: Principal point u (pixels; pixel centres at integers).
        cy: Principal point v (pixels).
        intrinsics: JSON with fx, fy, cx, cy (top level or under "intrinsics"); flags override it.
        depth_unit: Unit of a depth .npy (auto: integers or values over 20 are millimetres).
        port: Port on 127.0.0.1 (0: any free port).
        open: Open the page in the default web browser.
    """
    cfg = ClickConfig(image=image, out=out, fx=fx, fy=fy, cx=cx, cy=cy, intrinsics=intrinsics,
                      depth_unit=depth_unit, port=port, open=open)
    server = make_click_server(cfg)
    viewer.run_local(server, open, ready=lambda url: print(f"clicking {image} at {url} -> {out} (Ctrl-C stops)", flush=True))
    print("click page stopped")


def cache(build: bool = True) -> None:
    """Show the cache directory and build the Anny body-model cache if missing.

    Args:
        build: Build the Anny cache now (about a minute, once).
    """
    root = cache_dir()
    if build:
        load_anny()
    size = sum(p.stat().st_size for p in Path(root).rglob("*") if p.is_file())
    print(f"{root} ({size / 1e6:.0f} MB)")


__all__ = ["cache", "click", "view"]

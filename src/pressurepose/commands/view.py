"""`pressurepose view` and `pressurepose click`: the local web pages (`viz.viewer`,
`viz.clicker`), and `pressurepose cache`."""

from __future__ import annotations

from pathlib import Path

from pressurepose.body.anny_backend import load_anny
from pressurepose.cache import cache_dir
from pressurepose.viz import viewer
from pressurepose.viz.clicker import ClickConfig, make_click_server
from pressurepose.viz.viewer import ViewConfig, serve


def view(cfg: ViewConfig) -> None:
    """Browse samples and predictions in a local web page on 127.0.0.1: pressure images, true
    and estimated 3D bodies, joint errors, training curves (docs/viewer.md). Ctrl-C stops it."""
    serve(cfg, ready=lambda url: print(f"viewing {cfg.path} at {url} (Ctrl-C stops)", flush=True))
    print("viewer stopped")


def click(cfg: ClickConfig) -> None:
    """Click the mat's corner markers in a camera image on a local web page (127.0.0.1) and
    save the marker file `coregister --markers` reads (docs/real_data.md). Ctrl-C stops it."""
    server = make_click_server(cfg)
    viewer.run_local(
        server,
        cfg.open,
        ready=lambda url: print(f"clicking {cfg.image} at {url} -> {cfg.out} (Ctrl-C stops)", flush=True),
    )
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

"""A local page server (`viz.viewer.LocalServer`: the viewer, `pressurepose click`) run in a
thread on a free port for the tests, and the fixture body that opens any number of them and
closes them all. Shared by test_viewer.py and test_clicker.py."""

import threading


class Served:
    """`server` serving in a daemon thread; `url` its address."""

    def __init__(self, server) -> None:
        self.server = server
        self.url = server.url
        self.thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.05}, daemon=True)
        self.thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def opened(make):
    """Fixture body: yields `start(*args, **kwargs)` -> make(*args, **kwargs), closes them all after."""
    servers = []

    def start(*args, **kwargs):
        servers.append(make(*args, **kwargs))
        return servers[-1]

    yield start
    for s in servers:
        s.close()

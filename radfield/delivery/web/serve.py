"""Serving a web folder (delivery/web/) over HTTP for `radfield view`: the files as they are, from
one address, until stopped. ES modules and the model's fetch need http://, not file://."""

from __future__ import annotations

import contextlib
import functools
import http.server
import threading
from collections.abc import Iterator
from pathlib import Path

PORT_TRIES = 20    # a taken port: the next free one of this many


class _QuietHandler(http.server.SimpleHTTPRequestHandler):
    """The standard static-file handler without a log line per request."""

    extensions_map = {**http.server.SimpleHTTPRequestHandler.extensions_map, ".js": "text/javascript",
                      ".bin": "application/octet-stream", ".json": "application/json"}

    def log_message(self, format, *args) -> None:
        pass


def web_server(folder: Path, host: str, port: int) -> http.server.ThreadingHTTPServer:
    """An HTTP server of `folder` on `host`: on `port`, or the next free one if it is taken (0: any
    free port). Raises OSError when none of PORT_TRIES ports can be had."""
    handler = functools.partial(_QuietHandler, directory=str(folder))
    error = None
    for candidate in ([0] if port == 0 else range(port, min(port + PORT_TRIES, 65536))):
        try:
            return http.server.ThreadingHTTPServer((host, candidate), handler)
        except OSError as e:
            error = e
    raise error


@contextlib.contextmanager
def serving(httpd: http.server.ThreadingHTTPServer) -> Iterator[str]:
    """Serve from a thread while inside; yields the URL (http://HOST:PORT/)."""
    thread = threading.Thread(target=httpd.serve_forever, daemon=True)
    thread.start()
    try:
        host, port = httpd.server_address[:2]
        yield f"http://{host}:{port}/"
    finally:
        httpd.shutdown()
        httpd.server_close()

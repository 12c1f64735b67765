"""The monitor's web page: a small HTTP server (standard library) on a loopback address by default.

* ``GET /`` -- the page (``static/index.html`` + ``static/monitor.js``, plain HTML/JS/canvas, no
  external resource: it works without internet);
* ``GET /api/state`` -- the latest snapshot as JSON (``MonitorState.refresh``); the page polls it
  every ``POLL_MS`` (200 ms), so a change reaches the page within one monitor refresh + one poll.
  The JSON text is made once per snapshot, however many pages poll.
"""
from __future__ import annotations

import json
import threading
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from typing import Callable

STATIC = Path(__file__).resolve().parent / "static"
FILES = {"/": ("index.html", "text/html; charset=utf-8"),
         "/index.html": ("index.html", "text/html; charset=utf-8"),
         "/monitor.js": ("monitor.js", "text/javascript; charset=utf-8")}


def parse_host_port(text: str, default_host: str = "127.0.0.1") -> tuple[str, int]:
    """``HOST:PORT``, ``:PORT`` or ``PORT`` -> (host, port); host defaults to loopback."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "", text
    try:
        p = int(port)
    except ValueError:
        raise ValueError(f"--web {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8080") from None
    if not 0 <= p < 65536:
        raise ValueError(f"--web {text!r}: port outside 0..65535")
    return host or default_host, p


class WebServer:
    """Serves the page and ``/api/state`` from ``snapshot()`` on ``(host, port)`` (port 0: the OS
    picks one; ``url`` says which)."""

    def __init__(self, snapshot: Callable[[], dict | None], host: str = "127.0.0.1", port: int = 0):
        self._snapshot = snapshot
        self._cache: tuple[int, bytes] = (-1, b"null")
        self._cache_lock = threading.Lock()
        self.requests = 0
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 (http.server's name)
                outer.requests += 1
                path = self.path.split("?", 1)[0]
                if path == "/api/state":
                    self._send(HTTPStatus.OK, "application/json", outer.state_json())
                elif path in FILES:
                    name, ctype = FILES[path]
                    self._send(HTTPStatus.OK, ctype, (STATIC / name).read_bytes())
                else:
                    self._send(HTTPStatus.NOT_FOUND, "text/plain", b"not found")

            def _send(self, code: int, ctype: str, data: bytes) -> None:
                self.send_response(code)
                self.send_header("Content-Type", ctype)
                self.send_header("Content-Length", str(len(data)))
                self.send_header("Cache-Control", "no-store")
                self.end_headers()
                self.wfile.write(data)

            def log_message(self, *args) -> None:   # no access log on the terminal table
                pass

        self.httpd = ThreadingHTTPServer((host, port), Handler)
        self.httpd.daemon_threads = True
        self.host, self.port = self.httpd.server_address[:2]
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="v2xpos-monitor-web", daemon=True)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/"

    def state_json(self) -> bytes:
        snap = self._snapshot()
        if snap is None:
            return b"null"
        with self._cache_lock:
            if self._cache[0] != snap["version"]:
                self._cache = (snap["version"], json.dumps(snap, separators=(",", ":")).encode())
            return self._cache[1]

    def start(self) -> "WebServer":
        self._thread.start()
        return self

    def close(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()

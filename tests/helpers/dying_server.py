"""A real HTTP server process for tests: serves one folder with Range support and exits (the whole process, so
every connection is cut and later ones are refused) when asked for more than N ranges.

Usage: ``python dying_server.py FOLDER N PORTFILE`` (writes its port to PORTFILE once it listens).
"""

from __future__ import annotations

import http.server
import os
import re
import sys
from pathlib import Path


def main() -> None:
    """Serve ``argv[1]``; exit after ``argv[2]`` range requests; port written to ``argv[3]``."""
    root, limit, portfile = Path(sys.argv[1]), int(sys.argv[2]), Path(sys.argv[3])
    served = [0]

    class Handler(http.server.BaseHTTPRequestHandler):
        protocol_version = "HTTP/1.1"

        def log_message(self, *args: object) -> None:
            pass

        def _file(self) -> Path | None:
            path = root / self.path.lstrip("/").split("?")[0]
            return path if path.is_file() else None

        def do_HEAD(self) -> None:  # noqa: N802 - http.server's name
            path = self._file()
            if path is None:
                self.send_error(404)
                return
            self.send_response(200)
            self.send_header("Content-Length", str(path.stat().st_size))
            self.send_header("Accept-Ranges", "bytes")
            self.end_headers()

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            path = self._file()
            if path is None:
                self.send_error(404)
                return
            data = path.read_bytes()
            match = re.fullmatch(r"bytes=(\d+)-(\d*)", self.headers.get("Range", ""))
            if match is None:
                self.send_response(200)
                self.send_header("Content-Length", str(len(data)))
                self.end_headers()
                self.wfile.write(data)
                return
            if served[0] >= limit:
                os._exit(0)  # the server dies: this connection closes unanswered, later ones are refused
            served[0] += 1
            start = int(match.group(1))
            end = min(int(match.group(2) or len(data) - 1), len(data) - 1)
            self.send_response(206)
            self.send_header("Content-Range", f"bytes {start}-{end}/{len(data)}")
            self.send_header("Content-Length", str(end - start + 1))
            self.send_header("Accept-Ranges", "bytes")
            self.end_headers()
            self.wfile.write(data[start:end + 1])
            self.wfile.flush()

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    portfile.write_text(str(server.server_address[1]))
    server.serve_forever()


if __name__ == "__main__":
    main()

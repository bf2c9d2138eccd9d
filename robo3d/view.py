"""``robo3d view``: every stage's rerun log of one recording, opened together with a
designed layout (a rerun blueprint), in a native viewer or served to a browser.

The stages log into one entity tree (:mod:`robo3d.viz`); :func:`scan_blueprint` lays it
out from the entities the logs hold: a large 3D view in ``base`` with one subtree per
stage, the clutter hidden at first (ground truth, raw sweeps, every camera at once, voxels,
boxes, the hull and the fused mesh around and under the final one); beside it the current
silhouette view with its mask and the current laser frame with its stripe; below them the
scan's key figures as a short text, the scalars along the timelines, and each stage's
short report. The timeline
shown first is the recording's clock (``time``); ``view``, ``frame`` and ``sweep`` step
through the views, laser frames and sweeps.

Privacy: the servers rerun starts (the native viewer's own gRPC port, the web viewer and
its gRPC proxy) listen on 127.0.0.1 unless ``bind`` says otherwise, and the viewer we start
sends no usage data unless ``analytics`` is set:

- the native viewer and rerun's servers read their analytics setting from
  ``$XDG_CONFIG_HOME/rerun/analytics.json`` (rerun 0.41, ``re_analytics``), which
  :func:`rerun_environment` points at a private folder holding ``analytics_enabled:
  false`` (the user's own rerun config is not touched);
- the web viewer runs in the user's browser, and rerun 0.41's wasm reports usage from
  there whatever that file says (measured: four requests to ``tel.rerun.io`` per page
  load, plus ``api.github.com`` and ``app.rerun.io``). So the page is served through
  :class:`_CspProxy`, which adds a Content-Security-Policy that lets the page connect
  only to itself and rerun's gRPC server on this machine: the browser blocks the rest.
"""

from __future__ import annotations

import json
import logging
import os
import re
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

from .errors import Robo3dError
from .info import STAGES
from .viz import APPLICATION_ID

__all__ = [
    "STAGE_ORDER",
    "HIDDEN_AT_FIRST",
    "stage_logs",
    "logged_entities",
    "entity_rows",
    "scan_blueprint",
    "save_blueprint",
    "rerun_environment",
    "rerun_command",
    "web_viewer_url",
    "content_security_policy",
    "view_recording",
]

log = logging.getLogger(__name__)

#: The stages' logs in the order of the data flow (``results/<rec>/<stage>.rrd``): the
#: workflow's stages, as :mod:`robo3d.info` lists them.
STAGE_ORDER = STAGES

#: Subtrees of the 3D view hidden at first (the user ticks them on in the blueprint
#: panel): what lies on top of the result and hides it.
HIDDEN_AT_FIRST = (
    "base/silhouettes/workspace",   # boxes around the object
    "base/carve/box",
    "base/carve/hull",              # the visual hull, around the final mesh
    "base/carve/cameras",           # every view's frustum at once (the current one shows)
    "base/carve/left_out",
    "base/carve/voxels",            # the hull's voxels, under its mesh
    "base/triangulate",             # the raw sweeps, before alignment
    "base/fuse",                    # the fused mesh, under the final one
    "base/evaluate/ground_truth",
)

_URL = re.compile(r"(https?://[0-9A-Za-z.:\[\]-]+/?\?url=\S+)")


def stage_logs(results: str | os.PathLike[str]) -> list[Path]:
    """The ``.rrd`` files in a recording's results folder, the stages' first in data-flow
    order, then any other; :class:`Robo3dError` when there is none."""
    folder = Path(results)
    if not folder.is_dir():
        raise Robo3dError(f"{folder}: no such results folder (run the workflow first, or "
                          "give --results)")
    found = sorted(folder.glob("*.rrd"))
    if not found:
        raise Robo3dError(f"{folder}: no rerun log (*.rrd) in it")
    rank = {name: i for i, name in enumerate(STAGE_ORDER)}
    return sorted(found, key=lambda p: (rank.get(p.stem, len(rank)), p.name))


def logged_entities(paths: Iterable[str | os.PathLike[str]]) -> set[str]:
    """The entity paths the logs hold (without the leading ``/``), read from each file's
    manifest, not its data."""
    from rerun.chunk import RrdReader

    out: set[str] = set()
    for path in paths:
        out.update(e.lstrip("/") for e in RrdReader(path).store().schema().entity_paths())
    return out


def entity_rows(path: str | os.PathLike[str]) -> Counter[str]:
    """Rows logged per entity path (leading ``/`` dropped) in one ``.rrd`` file, reading
    every chunk (for tests and checks: what a stage logged, and how often)."""
    from rerun.chunk import RrdReader

    rows: Counter[str] = Counter()
    for chunk in RrdReader(path).stream():
        rows[chunk.entity_path.lstrip("/")] += chunk.num_rows
    return rows


def _present(entities: set[str], path: str) -> bool:
    return any(e == path or e.startswith(path + "/") for e in entities)


def scan_blueprint(entities: Iterable[str]) -> Any:
    """The designed layout (a ``rerun.blueprint.Blueprint``) for the entities logged.

    The 3D view takes two thirds of the width; the right column holds the current view
    with its mask, the current laser frame with its stripe, and a tab container of the
    scan's summary, the scalars and the stages' reports. Views only for what was logged:
    no panel says "no data". The final mesh coloured by its error replaces the one
    coloured by provenance when ground truth exists.
    """
    import rerun.blueprint as rrb

    ents = set(entities)
    hidden = [p for p in HIDDEN_AT_FIRST if _present(ents, p)]
    if _present(ents, "base/evaluate/mesh_error"):
        hidden.append("base/simplify/mesh")
    view3d = rrb.Spatial3DView(
        origin="base", contents="$origin/**", name="scan in base",
        overrides={p: rrb.EntityBehavior(visible=False) for p in hidden})
    right: list[Any] = []
    for origin, name in (("base/silhouettes/camera", "view + mask"),
                         ("base/stripes/camera", "laser frame + stripe")):
        if _present(ents, origin):
            right.append(rrb.Spatial2DView(origin=origin, contents="$origin/**", name=name))
    tabs: list[Any] = []
    if _present(ents, "reports/summary"):
        tabs.append(rrb.TextDocumentView(origin="reports/summary", name="summary"))
    if _present(ents, "metrics"):
        tabs.append(rrb.TimeSeriesView(origin="metrics", contents="$origin/**",
                                       name="per frame, per sweep"))
    for stage in STAGE_ORDER:
        if _present(ents, f"reports/{stage}"):
            tabs.append(rrb.TextDocumentView(origin=f"reports/{stage}", name=stage))
    if tabs:
        right.append(rrb.Tabs(*tabs, active_tab=0))
    main: Any = view3d
    if right:
        column = rrb.Vertical(*right, row_shares=[1.0] * len(right))
        main = rrb.Horizontal(view3d, column, column_shares=[2.0, 1.0])
    return rrb.Blueprint(
        main,
        rrb.BlueprintPanel(state="collapsed"),
        rrb.SelectionPanel(state="collapsed"),
        rrb.TimePanel(state="expanded", timeline="time", play_state="following"),
        auto_layout=False, auto_views=False)


def save_blueprint(path: str | os.PathLike[str], entities: Iterable[str]) -> Path:
    """Write :func:`scan_blueprint` as a rerun blueprint file (``.rbl``) for the
    application id the stages log under, so that ``rerun <logs> <file>.rbl`` applies it."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    scan_blueprint(entities).save(APPLICATION_ID, str(out))
    return out


def rerun_environment(config_dir: str | os.PathLike[str], *, analytics: bool = False
                      ) -> dict[str, str]:
    """The environment for the rerun process: with ``analytics`` False, rerun's config
    folder (``$XDG_CONFIG_HOME/rerun``) is a private ``config_dir`` whose
    ``analytics.json`` turns usage data off (rerun 0.41 reads it there; the user's own
    file is not touched); with True, the user's environment as it is."""
    env = dict(os.environ)
    if analytics:
        return env
    folder = Path(config_dir)
    (folder / "rerun").mkdir(parents=True, exist_ok=True)
    settings = {"analytics_enabled": False, "analytics_id": "robo3d-view-disabled",
                "metadata": {}, "config_file_path": str(folder / "rerun" / "analytics.json"),
                "data_dir_path": str(folder / "analytics-data")}
    (folder / "rerun" / "analytics.json").write_text(json.dumps(settings), encoding="utf-8")
    env["XDG_CONFIG_HOME"] = str(folder)
    return env


def rerun_command(files: Sequence[str | os.PathLike[str]], *, web: bool = False,
                  bind: str = "127.0.0.1", web_port: int = 9090, grpc_port: int = 9876
                  ) -> list[str]:
    """The rerun command line that opens ``files`` (logs and a blueprint): the native
    viewer, or with ``web`` the web viewer served over HTTP (no browser opened), each
    server bound to ``bind``; port 0 picks a free one."""
    cmd = [_rerun_executable(), "--bind", bind, "--port", str(grpc_port)]
    if web:
        cmd += ["--serve-web", "--web-viewer-port", str(web_port)]
    return cmd + [str(f) for f in files]


def _rerun_executable() -> str:
    """The rerun binary itself (``rerun_cli/rerun``), not the ``rerun`` console script,
    which runs it as a child of its own: stopping the script would leave the viewer's
    servers running."""
    try:
        import rerun_cli

        exe = Path(rerun_cli.__file__).with_name("rerun" + (".exe" if os.name == "nt" else ""))
        if exe.exists():
            return str(exe)
    except ImportError:
        pass
    script = Path(sys.executable).with_name("rerun")
    return str(script) if script.exists() else "rerun"


def web_viewer_url(rerun_line: str, bind: str) -> str | None:
    """The address to open, from rerun's "Hosting a web-viewer ... connect at <url>"
    line, with the gRPC proxy named by the bind address (rerun names it ``localhost``)."""
    m = _URL.search(rerun_line)
    if not m:
        return None
    url = m.group(1)
    if bind not in ("0.0.0.0", "::"):
        url = url.replace("localhost", bind if ":" not in bind else f"[{bind}]")
    return url


def _has_display() -> bool:
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
                or sys.platform in ("darwin", "win32"))


def view_recording(results: str | os.PathLike[str], *, web: bool = False,
                   bind: str = "127.0.0.1", web_port: int = 9090, grpc_port: int = 9876,
                   analytics: bool = False, announce: Callable[[str], None] | None = None,
                   start_timeout_s: float = 60.0) -> int:
    """Open a recording's logs with :func:`scan_blueprint` and wait until the viewer
    ends (Ctrl-C stops the web server); returns rerun's exit status.

    With ``web``, the address to open is passed to ``announce`` (default: a line on
    stdout) once rerun serves it.
    Without a display and without ``web``, a :class:`Robo3dError` says to use ``--web``
    (rerun's native viewer would fail with a window-system error).
    """
    logs = stage_logs(results)
    if not web and not _has_display():
        raise Robo3dError("no display (neither DISPLAY nor WAYLAND_DISPLAY is set): use "
                          "`robo3d view --web` and open the address it prints in a browser")
    with tempfile.TemporaryDirectory(prefix="robo3d-view-") as tmp:
        blueprint = save_blueprint(Path(tmp) / "view.rbl", logged_entities(logs))
        env = rerun_environment(Path(tmp) / "config", analytics=analytics)
        # without analytics, rerun serves its page on a free port, behind _CspProxy
        cmd = rerun_command([*logs, blueprint], web=web, bind=bind,
                            web_port=web_port if analytics else 0, grpc_port=grpc_port)
        log.debug("running %s", " ".join(cmd))
        if not web:
            return subprocess.call(cmd, env=env)
        return _serve(cmd, env, bind, web_port, announce or _print_line, start_timeout_s,
                      analytics)


def _print_line(text: str) -> None:
    sys.stdout.write(text + "\n")
    sys.stdout.flush()


def content_security_policy(grpc_origin: str) -> str:
    """The policy the web viewer's page is served with when usage data is off: fetches
    and sockets only to the page's own server and rerun's gRPC server, fonts and styles
    only from the page (rerun's wasm otherwise reports to ``tel.rerun.io`` and asks
    ``api.github.com`` and ``app.rerun.io`` from the browser)."""
    return (f"connect-src 'self' {grpc_origin}; font-src 'self' data:; "
            "style-src 'self' 'unsafe-inline'")


class _CspProxy:
    """A local HTTP server in front of rerun's web-viewer server: every response passed
    on as it is, with :func:`content_security_policy` added. Serves on a thread until
    :meth:`close`."""

    def __init__(self, upstream: str, bind: str, port: int, policy: str) -> None:
        import http.client
        import http.server
        import threading
        from urllib.parse import urlsplit

        target = urlsplit(upstream)

        class Handler(http.server.BaseHTTPRequestHandler):
            def do_GET(self) -> None:  # noqa: N802 - the http.server API
                conn = http.client.HTTPConnection(target.hostname, target.port, timeout=60)
                try:
                    conn.request("GET", self.path, headers={
                        k: v for k, v in self.headers.items()
                        if k.lower() in ("accept", "accept-encoding", "range")})
                    resp = conn.getresponse()
                    self.send_response(resp.status)
                    for k, v in resp.getheaders():
                        if k.lower() not in ("connection", "transfer-encoding",
                                             "content-security-policy"):
                            self.send_header(k, v)
                    self.send_header("Content-Security-Policy", policy)
                    self.end_headers()
                    while chunk := resp.read(1 << 20):
                        self.wfile.write(chunk)
                except (OSError, http.client.HTTPException):
                    pass  # the browser went away, or rerun did
                finally:
                    conn.close()

            def log_message(self, *args: Any) -> None:
                pass

        self.server = http.server.ThreadingHTTPServer((bind, port), Handler)
        self.server.daemon_threads = True
        self.port = int(self.server.server_address[1])
        threading.Thread(target=self.server.serve_forever, daemon=True).start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _wait_for_url(lines: Any, bind: str, timeout_s: float) -> str:
    """rerun's web-viewer address from its log lines (a queue), within ``timeout_s``."""
    import queue

    seen: list[str] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(0.0, deadline - time.monotonic()))
        except queue.Empty:
            break
        if line is None:
            break
        seen.append(re.sub(r"\x1b\[[0-9;]*m", "", line).rstrip())
        if url := web_viewer_url(seen[-1], bind):
            return url
    raise Robo3dError(f"rerun did not start its web viewer within {timeout_s:g} s: "
                      + (seen[-1] if seen else "no message"))


def _serve(cmd: list[str], env: dict[str, str], bind: str, web_port: int,
           announce: Callable[[str], None], start_timeout_s: float, analytics: bool) -> int:
    """Run rerun's web server, announce the address to open (within
    ``start_timeout_s``), pass rerun's messages on to our stderr, and stop it on Ctrl-C
    or SIGTERM. Without ``analytics`` rerun serves the page on a private port and
    :class:`_CspProxy` serves it on ``web_port``."""
    import queue
    import signal
    import threading
    from urllib.parse import unquote, urlsplit

    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            text=True, errors="replace")
    lines: queue.Queue[str | None] = queue.Queue()

    def _read() -> None:  # rerun's log lines, read beside us so that waiting is bounded
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.put(line)
        lines.put(None)

    def _stop(*_: Any) -> None:
        raise KeyboardInterrupt

    threading.Thread(target=_read, daemon=True).start()
    previous = signal.signal(signal.SIGTERM, _stop)
    proxy = None
    try:
        url = _wait_for_url(lines, bind, start_timeout_s)
        if not analytics:
            page = urlsplit(url)
            grpc = urlsplit(unquote(page.query.split("url=", 1)[1].split("&", 1)[0]))
            # the gRPC server as the browser will name it (any host when not loopback)
            grpc_origin = (f"http://{grpc.netloc}" if bind in ("127.0.0.1", "::1")
                           else f"http://*:{grpc.port}")
            proxy = _CspProxy(f"http://127.0.0.1:{page.port}", bind, web_port,
                              content_security_policy(grpc_origin))
            url = url.replace(page.netloc, f"{page.hostname}:{proxy.port}", 1)
        announce(f"robo3d view: open {url} (Ctrl-C stops the server)")
        while (line := lines.get()) is not None:
            sys.stderr.write(line)
        return proc.wait()
    except KeyboardInterrupt:
        return 0
    finally:
        signal.signal(signal.SIGTERM, previous)
        if proxy is not None:
            proxy.close()
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()

"""`bf-epic run --serve HOST:PORT`: the pipeline's metrics and health over HTTP, beside the run.

aiohttp serves, in a thread of its own with its own event loop (so that many or slow clients wait on
sockets, never on the pipeline's threads):

* ``GET /metrics``: Prometheus' text format (prometheus_client), from a :class:`~.monitor.Monitor`
  snapshot taken at each scrape;
* ``GET /health``: JSON ``{"status": "go" | "degraded" | "down", "reasons": [...], ...}``, HTTP 200, or
  503 when down (:func:`~.monitor.assess`);
* ``GET /``: a small status page that refreshes itself (health, key figures, the latest PNGs);
* ``GET /png/KEY``: one of the PNGs the run wrote that the page shows (:meth:`Service.pictures`);
* ``POST /trigger``: a triggered save (the watchlist's, ``watch:``) with the request body's first line as
  its reason; it changes state, so it needs the service's token (``Authorization: Bearer TOKEN``) and is
  refused (403) where no token is configured.

Nothing else is served: the PNGs are looked up by key among the run's own files, so no path in a
request reaches the disk. Requests over 64 KiB are refused (413);
header lines over aiohttp's 8 KiB limit are refused (400). The service binds to the loopback interface
unless the YAML's ``service.allow_remote`` says otherwise.
"""
from __future__ import annotations

import asyncio
import hmac
import html
import ipaddress
import logging
import re
import socket
import threading
import time

from .monitor import Limits, Monitor, assess

__all__ = ["Service", "parse_listen", "check_listen"]

log = logging.getLogger(__name__)

#: the largest request body accepted (a trigger's reason is one line)
MAX_REQUEST_BYTES = 64 * 1024
#: pending connections the listening socket holds (the kernel caps it at net.core.somaxconn)
BACKLOG = 1024


def parse_listen(text):
    """(host, port) of 'HOST:PORT', ':PORT' or 'PORT' (host 127.0.0.1); ValueError naming the problem."""
    text = str(text).strip()
    host, _, port = text.rpartition(":") if ":" in text else ("", "", text)
    host = host.strip("[]") or "127.0.0.1"
    try:
        port = int(port)
    except ValueError:
        raise ValueError(f"service.listen: {text!r} is not HOST:PORT (e.g. 127.0.0.1:8080)") from None
    if not 0 <= port <= 65535:
        raise ValueError(f"service.listen: port {port} is outside 0-65535")
    return host, port


def _is_loopback(host):
    try:
        return all(ipaddress.ip_address(a[4][0]).is_loopback
                   for a in socket.getaddrinfo(host, None, proto=socket.IPPROTO_TCP))
    except (OSError, ValueError):
        return False


def check_listen(host, allow_remote):
    """Refuse (ValueError) a non-loopback address unless ``allow_remote``."""
    if not allow_remote and not _is_loopback(host):
        raise ValueError(f"service.listen: {host} is not a loopback address; the service binds to this machine "
                         "only unless service.allow_remote: true (then put it behind the station's firewall)")


def _collector(monitor, get_snapshot):
    """A prometheus_client collector: each scrape's metrics from one snapshot."""
    from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily

    class SnapshotCollector:
        def collect(self):
            snap = get_snapshot()
            yield GaugeMetricFamily("bf_epic_up", "1 while the pipeline runs, 0 once it stopped or failed",
                                    value=0 if snap["failed"] or snap["finished"] else 1)
            for name, key, doc in (("uptime_seconds", "uptime_s", "seconds since the run started"),
                                   ("data_seconds", "data_s", "seconds of data the source has read"),
                                   ("realtime_factor", "realtime", "data seconds per wall second since the first data"),
                                   ("realtime_factor_recent", "realtime_recent", "the same over the last minute"),
                                   ("last_data_age_seconds", "last_data_age_s", "seconds since the source's last gulp")):
                if snap.get(key) is not None:
                    yield GaugeMetricFamily(f"bf_epic_{name}", doc, value=float(snap[key]))
            blocks = snap["blocks"]
            for key, kind, doc in (("ngulp", "counter", "gulps processed"),
                                   ("process_s", "counter", "seconds spent processing"),
                                   ("nframe_read", "counter", "frames read"),
                                   ("nframe_written", "counter", "frames written"),
                                   ("nframe_skipped", "counter", "frames skipped (lost to overruns)")):
                fam = (CounterMetricFamily if kind == "counter" else GaugeMetricFamily)(
                    f"bf_epic_block_{key}", f"each block's {doc}", labels=["block"])
                for name, st in blocks.items():
                    if key in st:
                        fam.add_metric([name], float(st[key]))
                yield fam
            per = GaugeMetricFamily("bf_epic_block_seconds_per_gulp", "each block's mean seconds per gulp",
                                    labels=["block"])
            for name, st in blocks.items():
                if st.get("ngulp"):
                    per.add_metric([name], float(st["process_s"]) / st["ngulp"])
            yield per
            for part in ("source", "source_lost_recent", "imager", "search", "watch", "solver", "flagging", "budget"):
                d = snap.get(part) or {}
                for k, v in sorted(d.items()):
                    if v is None:
                        continue
                    yield GaugeMetricFamily(re.sub(r"[^A-Za-z0-9_]", "_", f"bf_epic_{part}_{k}"), f"{part}: {k}",
                                            value=float(v))
            for part in ("disk", "gpu"):
                d = snap.get(part) or {}
                for k, v in sorted(d.items()):
                    yield GaugeMetricFamily(f"bf_epic_{part}_{k}", f"{part} {k.replace('_', ' ')}", value=float(v))
            for k, v in sorted((snap.get("memory") or {}).items()):
                unit = "" if k.endswith("_blocks") or k == "threads" else "_bytes"     # counts, not bytes
                yield GaugeMetricFamily(f"bf_epic_memory_{k}{unit}", f"this process's memory: {k.replace('_', ' ')} "
                                        "(bf_epic_blocks.service.heap.memory_figures)", value=float(v))
            status, _ = assess(snap, monitor.limits, monitor.cadence_s)
            yield GaugeMetricFamily("bf_epic_health", "0 go, 1 degraded, 2 down",
                                    value={"go": 0, "degraded": 1, "down": 2}[status])

    return SnapshotCollector()


_PAGE = """<!doctype html><html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1"><meta http-equiv="refresh" content="5">
<title>bf-epic: {name}</title><style>body{{font-family:sans-serif;margin:1em;max-width:50em}}
.go{{color:#080}}.degraded{{color:#a60}}.down{{color:#c00}}td{{padding:.1em .8em}}</style></head><body>
<h1>{name}</h1><p class="{status}"><b>{status}</b></p><ul>{reasons}</ul><table>{rows}</table>{candidates}{pictures}
<p><a href="/metrics">metrics</a> &middot; <a href="/health">health (JSON)</a></p></body></html>"""


class Service:
    """The HTTP service of one run (module docstring). ``start()`` binds and returns once it listens
    (``port`` is then the bound port, also for port 0); ``stop()`` closes it."""

    def __init__(self, monitor: Monitor, listen="127.0.0.1:0", allow_remote=False, token=None, bus=None,
                 limits=Limits(), cadence_s=None, name="bf-epic"):
        self.host, self.port = parse_listen(listen)
        check_listen(self.host, allow_remote)
        self.monitor, self.token, self.bus, self.name = monitor, token, bus, name
        monitor.limits, monitor.cadence_s = limits, cadence_s
        self.stats = {"requests": 0, "refused": 0, "triggers": 0}
        self._lock = threading.Lock()
        self._snap, self._snap_at = None, 0.0
        self._loop = self._runner = self._thread = None

    # the snapshot is shared by requests within 0.5 s of each other: 200 clients cost one snapshot
    def snapshot(self):
        with self._lock:
            now = time.monotonic()
            if self._snap is None or now - self._snap_at > 0.5:
                self._snap, self._snap_at = self.monitor.snapshot(), now
            return self._snap

    def pictures(self):
        """{key: path} of the PNGs the run has written that the page shows: ``image`` (the image writer's
        latest quicklook), ``candidates`` (the search's), ``lwatv`` (the latest LWATV view, ``output.oims``),
        ``watch-<target>`` (each watch target's). Only
        these are served, by key: no path in a request reaches the disk."""
        g = getattr(self.monitor, "g", None)
        out = {}
        if g is None:
            return out
        from pathlib import Path
        writer = getattr(g, "writer", None)
        pngs = [p for p in (getattr(writer, "written", None) or []) if str(p).endswith(".png")]
        if pngs:
            out["image"] = pngs[-1]
        cands = sorted(Path(g.outdir).glob("*_candidates.png")) if getattr(g, "outdir", None) else []
        if cands:
            out["candidates"] = str(cands[-1])
        lwatv = getattr(getattr(g, "oims", None), "pngs", None) or []
        if lwatv:
            out["lwatv"] = lwatv[-1]
        for p in (getattr(getattr(g, "watch", None), "pngs", None) or []):
            out["watch-" + Path(p).stem.rsplit("_", 1)[-1]] = p
        return {k: str(v) for k, v in out.items() if Path(v).is_file()}

    def _app(self):
        from aiohttp import web
        from prometheus_client import CollectorRegistry, generate_latest
        from prometheus_client.exposition import CONTENT_TYPE_LATEST
        registry = CollectorRegistry()
        registry.register(_collector(self.monitor, self.snapshot))

        @web.middleware
        async def count(request, handler):
            self.stats["requests"] += 1
            try:
                resp = await handler(request)
            except web.HTTPException as e:
                if e.status >= 400:
                    self.stats["refused"] += 1
                raise
            if resp.status >= 400:
                self.stats["refused"] += 1
            return resp

        async def metrics(request):
            body = await asyncio.get_running_loop().run_in_executor(None, generate_latest, registry)
            return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})

        async def health(request):
            snap = await asyncio.get_running_loop().run_in_executor(None, self.snapshot)
            status, reasons = assess(snap, self.monitor.limits, self.monitor.cadence_s)
            body = {"status": status, "reasons": reasons, "uptime_s": snap["uptime_s"], "data_s": snap["data_s"],
                    "realtime": snap["realtime"], "last_data_age_s": snap["last_data_age_s"],
                    "images": (snap.get("imager") or {}).get("images")}
            return web.json_response(body, status=503 if status == "down" else 200)

        async def page(request):
            snap = await asyncio.get_running_loop().run_in_executor(None, self.snapshot)
            status, reasons = assess(snap, self.monitor.limits, self.monitor.cadence_s)
            fig = [("uptime", f"{snap['uptime_s']:.0f} s"),
                   ("data read", "-" if snap["data_s"] is None else f"{snap['data_s']:.1f} s"),
                   ("real-time factor", "-" if snap["realtime"] is None else f"x{snap['realtime']:.2f}"),
                   ("images", (snap.get("imager") or {}).get("images", "-")),
                   ("candidates", (snap.get("search") or {}).get("candidates", "-")),
                   ("watch rows", (snap.get("watch") or {}).get("rows", "-"))]
            stamp = int(snap["uptime_s"])
            pics = "".join(f'<figure><img src="/png/{html.escape(k)}?t={stamp}" alt="{html.escape(k)}" '
                           f'style="max-width:100%"><figcaption>{html.escape(k)}</figcaption></figure>'
                           for k in sorted(self.pictures()))
            cands = snap.get("recent_candidates") or []
            table = "" if not cands else (
                "<h2>Recent candidates</h2><table><tr><th>UTC</th><th>S/N</th><th>DM</th><th>width ms</th>"
                "<th>RA</th><th>Dec</th><th></th></tr>" + "".join(
                    f"<tr><td>{html.escape(c['time_utc'])}</td><td>{c['snr']:.1f}</td><td>{c['dm']:.3f}</td>"
                    f"<td>{c['width_ms']:.2f}</td><td>{c['ra_deg']:.2f}</td><td>{c['dec_deg']:.2f}</td>"
                    f"<td>{html.escape(c['kind'])}</td></tr>" for c in cands) + "</table>")
            text = _PAGE.format(name=html.escape(self.name), status=status, candidates=table,
                                reasons="".join(f"<li>{html.escape(r)}</li>" for r in reasons),
                                rows="".join(f"<tr><td>{k}</td><td>{html.escape(str(v))}</td></tr>" for k, v in fig),
                                pictures=pics)
            return web.Response(text=text, content_type="text/html")

        async def picture(request):
            path = self.pictures().get(request.match_info["key"])
            if path is None:
                raise web.HTTPNotFound(text="no such picture (see / for those there are)")
            return web.FileResponse(path, headers={"Cache-Control": "no-store"})

        async def trigger(request):
            if not self.token:
                return web.json_response({"error": "no token is configured (service.token or the variable "
                                                   "service.token_env names): this service changes nothing"},
                                         status=403)
            got = request.headers.get("Authorization", "")
            if not hmac.compare_digest(got.encode(), f"Bearer {self.token}".encode()):
                return web.json_response({"error": "a valid token is needed (Authorization: Bearer TOKEN)"},
                                         status=401)
            if self.bus is None:
                return web.json_response({"error": "this pipeline has no watchlist (watch:) to trigger"}, status=404)
            reason = (await request.text()).strip().splitlines()
            reason = (reason[0] if reason and reason[0] else "http")[:200]
            self.bus.request(f"http: {reason}")
            self.stats["triggers"] += 1
            return web.json_response({"posted": reason}, status=202)

        app = web.Application(client_max_size=MAX_REQUEST_BYTES, middlewares=[count])
        app.router.add_get("/", page)
        app.router.add_get("/metrics", metrics)
        app.router.add_get("/health", health)
        app.router.add_get("/png/{key}", picture)
        app.router.add_post("/trigger", trigger)
        return app

    def start(self):
        from aiohttp import web
        ready, err = threading.Event(), []

        def serve():
            loop = asyncio.new_event_loop()
            asyncio.set_event_loop(loop)
            self._loop = loop
            try:
                self._runner = web.AppRunner(self._app(), access_log=None, handle_signals=False, shutdown_timeout=1.0)
                loop.run_until_complete(self._runner.setup())
                # a backlog for a station's worth of pages and scrapes connecting at once (aiohttp's 128
                # drops the rest of a burst of 200)
                site = web.TCPSite(self._runner, self.host, self.port, backlog=BACKLOG)
                loop.run_until_complete(site.start())
                self.port = self._runner.addresses[0][1]
            except Exception as e:  # noqa: BLE001 - reported to start()'s caller
                err.append(e)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self._runner.cleanup())
            loop.close()

        self._thread = threading.Thread(target=serve, name="bf-epic-service", daemon=True)
        self._thread.start()
        ready.wait(30)
        if err:
            raise RuntimeError(f"service: cannot listen on {self.host}:{self.port}: {err[0]}") from err[0]
        log.info("service: http://%s:%d/ (metrics at /metrics, health at /health)", self.host, self.port)
        return self

    def stop(self):
        if self._loop is not None and self._thread is not None and self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(10)
        self._loop = self._thread = None

    @property
    def url(self):
        return f"http://{self.host}:{self.port}"


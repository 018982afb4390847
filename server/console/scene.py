"""The console's 3D view: one viser server, one private view per console page.

Each console page opens a *console* (:meth:`ConsoleScene.open_console`, ``POST /api/consoles``) and
embeds viser with ``?websocket=ws://host:port/c/<console_id>``: the websocket path binds the viser
client to that console, so a click in one operator's view sets only that console's target, and
every shape of a console (machine, targeting overlay, preview, throw) is client-scoped
(server.console.scene_view.ClientView). Nothing is shared between operators but the ground grid.

A drawing thread poses each console's machine from its latest MachineState at ``rate_hz``.
Clicks: viser reports a RAY (origin, direction, machine frame, z up); :func:`ground_point`
intersects it with z = 0; in 2D mode the point snaps to the throwing line; the reason a target
cannot be served is computed at once (``refusal``) and drawn, and the console page hears the new
target over live push (``on_console_change``). A console replaying a recorded throw
(server.console.scene_replay, the History page) shows the machine posed from the recording at the time its
page seeks to, instead of the live state.
"""

from __future__ import annotations

import http.cookies
import logging
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import viser

from runtime.throw_geometry import MIN_TARGET_DISTANCE_M
from server.accounts.auth import COOKIE_NAME as SESSION_COOKIE
from server.console.scene_replay import Replay, recorded_paths
from server.console.scene_view import ClientView, MachineGeometry, snap_to_line
from server.errors import Conflict, Denied, Limited, NotFound

log = logging.getLogger(__name__)

DARK, RED = (60, 60, 70), (200, 40, 40)
DEFAULT_BAND_M = (MIN_TARGET_DISTANCE_M, 10.7)
CONSOLE_TTL_S = 12 * 3600.0
OPERATOR_ONLY_CANVAS = "<style>body * { visibility: hidden !important; } canvas { visibility: visible !important; }</style>"
"""Injected into viser's page (a GUI HTML element): only the 3D canvas stays visible; hidden
elements cannot be hit by the mouse nor focused, and clicks on the canvas still reach viser."""
_FRAME_SCRIPT = (
    # Esc (E-STOP) pressed while the focus is in this frame: tell the console page
    "window.addEventListener('keydown', function (e) { if (e.key === 'Escape' || e.key === 'Esc') {"
    " e.preventDefault(); window.parent.postMessage({ slinger: 'estop' }, '*'); } }, true);"
    # a short one-finger tap on the canvas: replay it as a mouse click, which viser turns into a ray
    " var tap = null;"
    # (timed by the events' own time stamps: a busy page that handles them late still sees a tap)
    " window.addEventListener('touchstart', function (e) { var t = e.touches[0];"
    " tap = e.touches.length === 1 ? { x: t.clientX, y: t.clientY, at: e.timeStamp } : null; }, true);"
    " window.addEventListener('touchend', function (e) { var t = e.changedTouches[0]; var s = tap; tap = null;"
    " if (!s || Math.hypot(t.clientX - s.x, t.clientY - s.y) > 10 || e.timeStamp - s.at > 600) return;"
    " var c = document.elementFromPoint(t.clientX, t.clientY); if (!c || c.tagName !== 'CANVAS') return;"
    " ['pointerdown', 'mousedown', 'pointerup', 'mouseup', 'click'].forEach(function (type) {"
    " var init = { bubbles: true, cancelable: true, clientX: t.clientX, clientY: t.clientY, button: 0,"
    " buttons: /down/.test(type) ? 1 : 0, pointerId: 1, pointerType: 'mouse', isPrimary: true };"
    " c.dispatchEvent(/pointer/.test(type) ? new PointerEvent(type, init) : new MouseEvent(type, init)); }); }, true);"
    # frame-rate cap: at most FAST_FPS while the operator orbits, zooms or taps (the last second),
    # else IDLE_FPS: a view on software WebGL never takes the console page's main thread whole
    " var raf = window.requestAnimationFrame.bind(window), caf = window.cancelAnimationFrame.bind(window);"
    " var jobs = {}, nextId = 1, lastFrame = 0, lastInput = 0;"
    " ['pointerdown', 'pointermove', 'wheel', 'touchstart', 'keydown'].forEach(function (type) {"
    " window.addEventListener(type, function () { lastInput = performance.now(); }, { capture: true, passive: true }); });"
    " window.requestAnimationFrame = function (cb) { var id = nextId++; var now = performance.now();"
    " var gap = now - lastInput < 1000 ? 1000 / %(fast)d : 1000 / %(idle)d;"
    " var run = function () { jobs[id] = { r: raf(function (t) { delete jobs[id]; lastFrame = performance.now(); cb(t); }) }; };"
    " var wait = lastFrame + gap - now - 8; if (wait > 0) jobs[id] = { t: setTimeout(run, wait) }; else run(); return id; };"
    " window.cancelAnimationFrame = function (id) { var j = jobs[id]; delete jobs[id];"
    " if (j && j.t) clearTimeout(j.t); if (j && j.r) caf(j.r); };"
)
VIEW_FAST_FPS = 30
"""The 3D view's frame-rate cap while the operator moves the camera or taps (the last second)."""
VIEW_IDLE_FPS = 12
"""The 3D view's frame-rate cap otherwise (the machine's pose arrives at ConsoleScene.rate_hz)."""
ESTOP_KEY_FORWARD = ('<img alt="" src="data:," onerror="if (!window.__slingerKeys) { window.__slingerKeys = 1; '
                     + _FRAME_SCRIPT % {"fast": VIEW_FAST_FPS, "idle": VIEW_IDLE_FPS} + ' }">')
"""Injected into viser's page like OPERATOR_ONLY_CANVAS: Esc pressed while the focus is in the 3D
view (another origin: the console page cannot hear its keys) is posted to the console page, whose
status strip (web/js/strip.js) sends the E-STOP; a one-finger tap on a touch screen is replayed as
a mouse click (viser turns clicks, not taps, into target rays); the view's animation frames are capped
(VIEW_FAST_FPS / VIEW_IDLE_FPS). viser renders GUI HTML with
innerHTML, where a <script> does not run but an image's error handler does (the empty data: URL is
no image)."""
MAX_CONSOLES = 500
"""Consoles open on one server at most; past it a new one is refused (:class:`ConsoleLimit`),
never made by evicting another user's."""
MAX_CONSOLES_PER_USER = 16
"""Consoles one user keeps at most: a further page load closes that user's least recently used
console (an old tab), never another user's."""


class ConsoleLimit(Limited):
    """The server holds :data:`MAX_CONSOLES` consoles of other users; the message says so."""


class SceneDisabled(Conflict):
    """The 3D view is off on this server (``Settings.viser_enabled``)."""


def enabled(scene: ConsoleScene | None) -> ConsoleScene:
    """``scene`` when the 3D view runs.

    Raises:
        SceneDisabled: ``scene`` is None (the view is off).
    """
    if scene is None:
        raise SceneDisabled("the 3D view is disabled")
    return scene


def ground_point(ray_origin, ray_direction, max_range_m: float = 200.0) -> np.ndarray | None:
    """Intersection of a click ray with the ground plane z = 0.

    Args:
        ray_origin: (3,) ray origin, machine frame, m.
        ray_direction: (3,) ray direction (any length).
        max_range_m: ignore hits farther than this from the turn axis (near-horizon clicks).

    Returns:
        (3,) point with z = 0, or None if the ray does not point down to the ground.
    """
    o = np.asarray(ray_origin, dtype=float)
    d = np.asarray(ray_direction, dtype=float)
    if d[2] >= -1e-9 or o[2] <= 0.0:
        return None
    p = o + (-o[2] / d[2]) * d
    if not np.all(np.isfinite(p)) or np.hypot(p[0], p[1]) > max_range_m:
        return None
    p[2] = 0.0
    return p


def _segments(points) -> np.ndarray:
    p = np.asarray(points, dtype=float)
    return np.stack([p[:-1], p[1:]], axis=1)


@dataclass
class Console:
    """One console page's view state (outlives viser reconnects).

    Attributes:
        machine_id / mode: what the operator looks at; target (3,) m or None, with
        ``target_reason`` (why it cannot be served, None if it can) and ``snapped`` (moved onto
        the 2D line). ``preview_names``: the scene names of the drawn preview. ``replay``: the
        recorded throw the view replays (server.console.scene_replay), None for the live machine.
    """

    console_id: str
    username: str
    machine_id: str | None = None
    mode: str = "2d"
    target: list[float] | None = None
    target_reason: str | None = None
    snapped: bool = False
    preview_names: list[str] = field(default_factory=list)
    touched: float = field(default_factory=time.monotonic)
    replay: Replay | None = None
    view_token: str = field(default_factory=lambda: secrets.token_urlsafe(18))
    """The secret in the view's websocket path (/c/<console_id>/<view_token>) that binds the view
    to this console without a session cookie: the console page serves the view from another host
    name (its own renderer process), to which the browser sends no cookie of the console's."""

    def public(self) -> dict:
        return {"console_id": self.console_id, "machine_id": self.machine_id, "mode": self.mode,
                "target": self.target, "target_reason": self.target_reason, "snapped": self.snapped,
                "preview": list(self.preview_names), "replay": self.replay.public() if self.replay else None}


class ConsoleScene:
    """The 3D view server. :meth:`start` serves it; :meth:`stop` shuts it down.

    Args:
        fleet: source of machine states (``latest_state``).
        host / port: where viser listens (it moves on to the next free port; read :attr:`port`).
        public_host: the host name pages load the view from (server.config.Settings.viser_public_host;
            None: the page decides, web/js/common.js viewHost).
        rate_hz: machine redraw rate.
        refusal: (machine_id, mode, target (3,)) -> reason the target cannot be served, or None.
        band: (machine_id, mode) -> the policy's trained target range (lo, hi) m, or None.
        zones: keep-out zones (server.config.KeepOutZone) drawn in every view.
        on_console_change: called with Console.public() after a click changed a console.
        authorise: session token (the ``slinger_session`` cookie the browser sends with the
            view's websocket; None when it sent none) -> the user name it logs in, or None. When
            given, a view is bound to its console only if that user owns the console: knowing a
            console's id is not enough to aim its operator's throws. None: every view binds
            (tests of the scene alone).
    """

    def __init__(self, fleet, host: str = "127.0.0.1", port: int = 8080, rate_hz: float = 20.0,
                 refusal: Callable | None = None, band: Callable | None = None, zones=(),
                 on_console_change: Callable[[dict], None] | None = None,
                 authorise: Callable[[str | None], str | None] | None = None, public_host: str | None = None):
        self.fleet = fleet
        self.public_host = public_host
        self.host, self.requested_port, self.rate_hz = host, port, rate_hz
        self.refusal = refusal or (lambda mid, mode, t: None)
        self.band = band or (lambda mid, mode: None)
        self.zones = list(zones)
        self.on_console_change = on_console_change
        self.authorise = authorise
        self.server: viser.ViserServer | None = None
        self.port: int | None = None
        self.consoles: dict[str, Console] = {}
        self.max_consoles, self.max_per_user = MAX_CONSOLES, MAX_CONSOLES_PER_USER
        self._views: dict[int, tuple[str | None, ClientView]] = {}
        """viser client id -> (its console id, None for a client without one; its view)."""
        self._geometry: MachineGeometry | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._lock = threading.RLock()

    # --- lifecycle -----------------------------------------------------------------------------
    def start(self) -> None:
        self._geometry = MachineGeometry()  # the twin's MJCF, evaluated with numpy (no MuJoCo here)
        self.server = viser.ViserServer(host=self.host, port=self.requested_port, label="Slinger", verbose=False)
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        # operators get the view only: viser 1.1 has no API to hide its control panel (the main
        # panel has no `visible`), so the panel's only content is a style that hides viser's whole
        # page but the WebGL canvas (labels are drawn in it): its panel, settings button, scene
        # tree and notifications are neither visible nor focusable nor clickable
        self.server.gui.configure_theme(control_width="small", show_share_button=False, show_logo=False)
        self.server.gui.add_html(OPERATOR_ONLY_CANVAS + ESTOP_KEY_FORWARD)
        self.server.scene.add_grid("/ground", width=40.0, height=40.0, cell_size=1.0, section_size=5.0,
                                   plane_color=(150, 165, 130), plane_opacity=0.35)
        self.server.on_client_connect(self._on_connect)
        self.server.on_client_disconnect(self._on_disconnect)
        self._thread = threading.Thread(target=self._run, name="scene-draw", daemon=True)
        self._thread.start()
        log.info("3D view on http://%s:%d", self.host, self.port)

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5.0)
        if self.server is not None:
            self.server.stop()
            self.server = None

    # --- consoles ------------------------------------------------------------------------------
    def open_console(self, username: str) -> Console:
        """A new console (one per page load) for ``username``.

        Consoles unused for CONSOLE_TTL_S are dropped first. A user who holds
        ``max_per_user`` consoles loses their own least recently used one; no user's page load
        ever closes another user's console.

        Raises:
            ConsoleLimit: ``max_consoles`` consoles are open and none is this user's.
        """
        now = time.monotonic()
        with self._lock:
            for cid in [c for c, v in self.consoles.items() if now - v.touched > CONSOLE_TTL_S]:
                del self.consoles[cid]
            own = [c for c, v in self.consoles.items() if v.username == username]
            if own and (len(own) >= self.max_per_user or len(self.consoles) >= self.max_consoles):
                del self.consoles[min(own, key=lambda c: self.consoles[c].touched)]
            elif len(self.consoles) >= self.max_consoles:
                raise ConsoleLimit(f"the server has {len(self.consoles)} consoles open, its limit: "
                                   "close a console page or wait for unused ones to expire")
            con = Console(secrets.token_hex(12), username)
            self.consoles[con.console_id] = con
        return con

    def get_console(self, console_id: str) -> Console | None:
        with self._lock:
            con = self.consoles.get(console_id)
            if con is not None:
                con.touched = time.monotonic()
            return con

    def owned_console(self, console_id: str, username: str) -> Console:
        """Console ``console_id`` of ``username`` (touched, as :meth:`get_console`).

        Raises:
            NotFound: no such console (closed, expired or never opened).
            Denied: the console belongs to another user.
        """
        con = self.get_console(console_id)
        if con is None:
            raise NotFound(f"no console {console_id} (reload the page)")
        if con.username != username:
            raise Denied("this console belongs to another user")
        return con

    def update_console(self, con: Console, machine_id: str | None = None, mode: str | None = None,
                       target=None, clear: bool = False) -> Console:
        """Change what a console shows; a new machine or mode, or ``clear`` (the page saw its
        machine's runtime restart), drops the old target, preview and throw drawings."""
        with self._lock:
            changed = clear or (machine_id is not None and machine_id != con.machine_id) or (mode is not None and mode != con.mode)
            if machine_id is not None:
                con.machine_id = machine_id
            if mode is not None:
                con.mode = mode
            if changed:
                con.target, con.target_reason, con.preview_names, con.replay = None, None, [], None
                for view in self._views_of(con.console_id):
                    view.clear("/preview", "/throw", "/target", "/band")
                    view.framed_for = view.drawn_for = None
            if target is not None:
                self._set_target(con, target)
            else:
                self._redraw_target(con)
        return con

    def _views_of(self, console_id: str) -> list[ClientView]:
        return [v for cid, v in self._views.values() if cid == console_id]

    def _set_target(self, con: Console, target) -> None:
        t = np.asarray(target, dtype=float)
        con.snapped = False
        state = self.fleet.latest_state(con.machine_id) if con.machine_id else None
        if con.mode == "2d" and state is not None:
            p = snap_to_line(t[:2], state.q[0])
            if p is not None:
                con.snapped = bool(np.hypot(*(p - t[:2])) > 1e-6)
                t = np.array([p[0], p[1], 0.0])
        con.target = [round(float(v), 3) for v in t]
        con.target_reason = self.refusal(con.machine_id, con.mode, con.target) if con.machine_id else "pick a machine first"
        con.preview_names = []
        for view in self._views_of(con.console_id):
            view.clear("/preview")
        self._redraw_target(con)

    def _redraw_target(self, con: Console) -> None:
        for view in self._views_of(con.console_id):
            view.draw_target(con.target, con.target_reason)

    # --- viser clients -------------------------------------------------------------------------
    def _request_of_client(self, client):
        """The websocket handshake request of a viser client (``path``, ``headers``), or None (a
        viser whose internals moved).

        The one private reach-in into viser, kept here alone: viser 1.1 has no public way to learn
        which URL a client connected with, or with which headers. Its public client API is
        :meth:`viser.ViserServer.get_clients` / :meth:`~viser.ViserServer.on_client_connect`,
        which hand a :class:`viser.ClientHandle` whose public attributes are ``client_id``,
        ``scene``, ``gui``, ``camera`` and ``local_storage``; the websocket request, and with it
        its path, is kept only in the private ``WebsockServer._live_connections``. The public
        ``local_storage`` cannot carry the console id instead: it is shared by every tab of the
        viser origin (two console pages open in one browser would overwrite each other's id),
        and it is read asynchronously after the connection, so the view would be unbound until
        a round trip to the browser answered. Covered by tests/test_server_scene.py (a view
        opened at /c/<console_id> draws that console's target)."""
        if self.server is None:
            return None
        try:
            return self.server._websock_server._live_connections[client.client_id].request  # noqa: SLF001 (see the docstring)
        except (AttributeError, KeyError):
            return None

    def _console_of_client(self, client) -> str | None:
        """The console id in the client's websocket path (/c/<console_id>[/<view_token>]), or None
        (a view opened outside a console page), if the client may bind to it: its path carries
        the console's view token, or (:attr:`authorise`) its cookie logs in the console's owner."""
        request = self._request_of_client(client)
        if request is None:
            return None
        path = request.path.split("?")[0]
        parts = [p for p in path.split("/") if p]
        cid = parts[1] if len(parts) in (2, 3) and parts[0] == "c" else None
        if cid is None:
            return None
        if len(parts) == 3:
            con = self.get_console(cid)
            if con is not None and secrets.compare_digest(parts[2], con.view_token):
                return cid
            log.warning("3D view for console %s… not bound: its view token is not the console's", cid[:6])
            return None
        if self.authorise is None:
            return cid
        cookie = http.cookies.SimpleCookie()
        try:
            cookie.load(request.headers.get("Cookie", ""))
        except http.cookies.CookieError:
            pass
        morsel = cookie.get(SESSION_COOKIE)
        user = self.authorise(morsel.value if morsel else None)
        con = self.get_console(cid)
        if con is None or user != con.username:
            log.warning("3D view for console %s… not bound: its websocket %s", cid[:6],
                        "carries no valid session" if user is None else f"is {user}'s, not the console owner's")
            return None
        return cid

    def _on_connect(self, client) -> None:
        if self._geometry is None:
            raise RuntimeError("a viser client connected before SceneServer.start")
        cid = self._console_of_client(client)
        view = ClientView(client, self._geometry)
        with self._lock:
            view.build(self.zones)
            self._views[client.client_id] = (cid, view)
        client.scene.on_click()(lambda event: self._on_click(client.client_id, event))
        con = self.get_console(cid) if cid else None
        if con is not None:
            self._redraw_target(con)

    def _on_disconnect(self, client) -> None:
        with self._lock:
            self._views.pop(client.client_id, None)

    def _on_click(self, client_id: int, event) -> None:
        with self._lock:
            cid = self._views.get(client_id, (None, None))[0]
        con = self.get_console(cid) if cid else None
        if con is None:
            return  # a view opened outside a console page: look only
        p = ground_point(event.ray_origin, event.ray_direction)
        if p is None:
            log.debug("click ray misses the ground: %s %s", event.ray_origin, event.ray_direction)
            return
        with self._lock:
            self._set_target(con, p.tolist())
        if self.on_console_change is not None:
            self.on_console_change(con.public())

    # --- replay of a recorded throw ------------------------------------------------------------
    def start_replay(self, con: Console, replay: Replay) -> None:
        """Replay ``replay`` in the console's views: its machine, the recorded paths, impact and
        target drawn, the machine posed from the recording at its shown time."""
        with self._lock:
            if con.machine_id != replay.machine_id:
                self.update_console(con, machine_id=replay.machine_id)
            con.replay = replay
            for view in self._views_of(con.console_id):
                view.clear("/preview", "/target")
                _draw_recorded(view, replay.gripper_path_m, replay.payload_path_m, replay.impact_m, replay.target_m)
                self._draw(con, view)

    def seek_replay(self, con: Console, t_s: float) -> float:
        """Show the console's replay at ``t_s`` (s from the recording's start, clamped), drawn
        in its views before this returns; returns the time shown.

        Raises:
            ValueError: the console replays nothing.
        """
        with self._lock:
            if con.replay is None:
                raise ValueError("this console replays no throw")
            shown = con.replay.seek(t_s)
            for view in self._views_of(con.console_id):
                self._draw(con, view)
        return shown

    def stop_replay(self, con: Console) -> None:
        """Back to the live machine: the replay and its drawn paths go."""
        with self._lock:
            con.replay = None
            for view in self._views_of(con.console_id):
                view.clear("/throw")

    def drawn_poses(self, console_id: str) -> list[np.ndarray | None]:
        """The joint positions (6,) each connected view of the console last drew (None: none
        yet): what the operator sees, for checks."""
        with self._lock:
            return [None if v.last_q is None else v.last_q.copy() for v in self._views_of(console_id)]

    # --- drawing -------------------------------------------------------------------------------
    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        while not self._stop.wait(period):
            with self._lock:
                views = [(self.consoles.get(cid) if cid else None, v) for cid, v in self._views.values()]
            for con, view in views:
                try:
                    self._draw(con, view)
                except Exception:
                    log.exception("drawing a console view failed")

    def _draw(self, con: Console | None, view: ClientView) -> None:
        # Decided and drawn under one hold of the lock: a drawing-thread pass that read "live" before
        # a replay started (or was sought) must not draw its live pose over the replayed one.
        with self._lock:
            replay = con.replay if con is not None else None
            mid = replay.machine_id if replay is not None else con.machine_id if con is not None else None
            if mid is None:
                ids = sorted(self.fleet.latest_states())
                mid = ids[0] if ids else None
            if replay is not None:
                q, payload = replay.pose()
                label = f"REPLAY of throw {replay.throw_id[:8]} on {mid}: t = {replay.shown_t_s:.2f} s"
            else:
                state = self.fleet.latest_state(mid) if mid else None
                if state is None:
                    return
                online = self.fleet.is_online(mid) if hasattr(self.fleet, "is_online") else True
                kind = "SIMULATED machine" if state.simulated else "machine"
                label = f"{kind} {mid}" + ("" if online else " (runtime OFFLINE: last known pose)")
                flying = state.payload_pos_m is not None and state.payload_attached is False
                q, payload = state.q, state.payload_pos_m if flying else None
            view.draw_machine(label, q, payload)
            mode = con.mode if con is not None else "2d"
            band = self.band(mid, mode) or DEFAULT_BAND_M
            key = (mid, mode, tuple(band), round(float(q[0]), 2) if mode == "2d" else None)
            if view.drawn_for != key:
                view.draw_band(mode, q[0], band)
                view.drawn_for = key
            if view.framed_for is None or view.framed_for[:2] != key[:2]:
                view.frame_camera(q[0], band, key)
            view.relabel()  # the camera, the gripper or a label moved: labels stay clear of each other

    # --- previews and throws -------------------------------------------------------------------
    def show_preview(self, con: Console, summary: dict) -> list[str]:
        """Draw a preview (server.console.scene_preview) in the views of ``con`` only."""
        from server.console.scene_preview import draw_preview, preview_labels

        names: list[str] = []
        with self._lock:
            for view in self._views_of(con.console_id):
                names = draw_preview(view.client, summary, summary.get("mode", con.mode))
                view.set_labels("/preview", preview_labels(summary))
            con.preview_names = names
            if summary.get("status") != "ok":
                con.target_reason = f"preview failed: {summary.get('reason')}"
                self._redraw_target(con)
        return names

    def show_throw(self, machine_id: str, telemetry_path: Path | None, impact_m, target_m) -> None:
        """Draw a finished throw (gripper path from the recorded joints, payload path, impact) in
        every view showing ``machine_id``. Missing telemetry just draws the impact."""
        gripper = payload = None
        if telemetry_path is not None and Path(telemetry_path).is_file():
            from runtime.telemetry import read_telemetry

            gripper, payload = recorded_paths(read_telemetry(telemetry_path))
        with self._lock:
            views = [v for cid, v in self._views.values() if cid in self.consoles and self.consoles[cid].machine_id == machine_id
                     and self.consoles[cid].replay is None]
        for view in views:
            _draw_recorded(view, gripper, payload, impact_m, target_m)


def _draw_recorded(view: ClientView, gripper, payload, impact_m, target_m) -> None:
    """A recorded throw under ``/throw`` in one view: the gripper centre's path (dark), the
    payload's (red), the impact with its distance from the target."""
    s = view.client.scene
    with view.client.atomic():
        s.remove_by_name("/throw")
        s.add_frame("/throw", show_axes=False)
        if gripper is not None:
            s.add_line_segments("/throw/gripper_path", _segments(gripper), DARK, thickness=0.06)
        if payload is not None:
            s.add_line_segments("/throw/payload_path", _segments(payload), RED, thickness=0.06)
        labels = []
        if impact_m is not None:
            s.add_icosphere("/throw/impact", radius=0.3, color=RED, position=tuple(impact_m))
            text = "impact"
            if target_m is not None:
                text = f"impact {math.hypot(impact_m[0] - target_m[0], impact_m[1] - target_m[1]):.2f} m from target"
            labels.append(("/throw/impact", impact_m, text))
        view.set_labels("/throw", labels)

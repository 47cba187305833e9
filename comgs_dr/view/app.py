"""The viser server of ``comgs view``: :class:`ViewerApp`.

The scene's surfels and each object's surfels are shown as points; each object hangs under
a transform gizmo (``/objects/<name>``). On a gizmo's release (not while it is dragged) the
object's move is queued: :meth:`ViewSession.move` re-runs the edit stage for it, then the
composite is rendered from the viewer's camera at ``res``² and shown in the GUI's image
panel, with the time from the release to the new image. The GUI also has, per object, its
position (a move typed in: "apply move" runs the same path as a release), and the buttons
"save placement" (``transform.json``), "render full size" (``COMP_DIR/view/full_*.png``)
and the variant (sop / trace / noshadow / paste). One worker thread does all the rendering
and editing, in order; a newer request of the same kind replaces one still waiting.

Every shown composite is also written to ``COMP_DIR/view/preview.png`` and a line per
update appended to ``COMP_DIR/view/log.jsonl`` (what was done, its seconds).
"""
from __future__ import annotations

import json
import logging
import threading
import time
import traceback
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from comgs_dr.data.images import write_png8
from comgs_dr.stages.render_comp import VARIANTS
from comgs_dr.view.session import (ViewSession, camera_pose_cv, rotation_wxyz, viewer_camera,
                                   wxyz_rotation)

log = logging.getLogger(__name__)

CAMERA_SETTLE_S = 0.4        # the camera must rest this long before a "follow" re-render


class _Worker(threading.Thread):
    """Runs jobs ``(key, fn)`` one at a time in submission order; a job submitted under a
    key that is still waiting replaces it (the newest move of an object, the newest
    render)."""

    def __init__(self, on_error: Callable[[BaseException], None]):
        super().__init__(daemon=True, name="comgs-view-worker")
        self.cv = threading.Condition()
        self.jobs: list = []
        self.busy = False
        self.on_error = on_error
        self.stopped = False

    def submit(self, key: str, fn: Callable[[], None]) -> None:
        with self.cv:
            self.jobs = [(k, f) for k, f in self.jobs if k != key]
            self.jobs.append((key, fn))
            self.cv.notify()

    def idle(self) -> bool:
        with self.cv:
            return not self.jobs and not self.busy

    def stop(self) -> None:
        with self.cv:
            self.stopped = True
            self.cv.notify()

    def run(self) -> None:
        while True:
            with self.cv:
                while not self.jobs and not self.stopped:
                    self.cv.wait()
                if self.stopped:
                    return
                _, fn = self.jobs.pop(0)
                self.busy = True
            try:
                fn()
            except BaseException as e:           # shown in the GUI; the viewer keeps running
                log.error("comgs view: %s", traceback.format_exc())
                self.on_error(e)
            finally:
                with self.cv:
                    self.busy = False


class ViewerApp:
    """The viewer of a :class:`ViewSession` (its ``cfg``: host, port, res, ...), serving at
    once; :attr:`port` is the port it listens on. :meth:`stop` ends it."""

    def __init__(self, session: ViewSession, say: Callable = print):
        import viser
        self.session, self.cfg, self.say = session, session.cfg, say
        self.out = session.comp / "view"
        self.out.mkdir(parents=True, exist_ok=True)
        (self.out / "log.jsonl").write_text("")
        self.frames = 0
        self.last_move = ""          # the status's second line: the last move and its time
        self.server = viser.ViserServer(host=self.cfg.host, port=self.cfg.port, verbose=False)
        self.port = self.server.get_port()
        self.server.scene.set_up_direction("+z")
        self.home = session.home_camera(self.cfg.res)
        self.worker = _Worker(self._error)
        self._add_scene()
        self._add_gui()
        self.server.on_client_connect(self._on_connect)
        self.worker.start()
        self.worker.submit("render", partial(self._render, None, "first frame", time.perf_counter()))

    # ------------------------------------------------------------------ scene

    def _add_scene(self) -> None:
        s = self.session
        pts, cols = s.scene_points()
        sizes = [float(np.linalg.norm(np.subtract(*s.bounds(n)))) for n in s.names]
        self.point_size = 0.01 * float(np.median(sizes))        # 1 % of an object's size
        self.server.scene.add_point_cloud("/scene", pts, cols, point_size=self.point_size,
                                          point_shape="circle")
        self.gizmos = {}
        for n in s.names:
            sim = s.world[n]
            blo, bhi = s.bounds(n)
            g = self.server.scene.add_transform_controls(
                f"/objects/{n}", scale=max(float(np.linalg.norm(bhi - blo)) * 0.6, 1e-6),
                position=tuple(sim.translation), wxyz=tuple(rotation_wxyz(sim.rotation)))
            p, c = s.object_points(n)
            self.server.scene.add_point_cloud(f"/objects/{n}/points",
                                              (p * sim.scale).astype(np.float32), c,
                                              point_size=self.point_size, point_shape="circle")
            g.on_update(partial(self._on_gizmo, n))
            self.gizmos[n] = g

    # ------------------------------------------------------------------ GUI

    def _add_gui(self) -> None:
        gui, cfg = self.server.gui, self.cfg
        h = w = cfg.res
        self.image = gui.add_image(np.zeros((h, w, 3), np.uint8), label="composite",
                                   format="png")
        self.status = gui.add_markdown("rendering the first frame ...")
        self.variant = gui.add_dropdown("variant", VARIANTS, initial_value=cfg.variant)
        self.variant.on_update(lambda _: self.worker.submit(
            "render", partial(self._render, None, f"variant {self.variant.value}",
                              time.perf_counter())))
        self.follow = gui.add_checkbox("re-render when the camera rests", initial_value=True)
        self.save_button = gui.add_button("save placement")
        self.save_button.on_click(lambda _: self.worker.submit("save", self._save))
        self.full_button = gui.add_button("render full size")
        self.full_button.on_click(lambda e: self.worker.submit(
            "full", partial(self._render_full, getattr(e, "client", None))))
        self.positions = {}
        for n in self.session.names:
            with gui.add_folder(f"object {n}"):
                pos = gui.add_vector3(f"{n} position", tuple(float(v) for v in
                                                            self.session.world[n].translation),
                                      step=0.001)
                apply = gui.add_button(f"apply move of {n}")
            apply.on_click(partial(self._on_apply, n))
            self.positions[n] = pos

    def _set_status(self, text: str) -> None:
        """The status: ``text``, then the last move's line (kept until the next move)."""
        self.status.content = text + (f"\n\n{self.last_move}" if self.last_move else "")

    def _error(self, e: BaseException) -> None:
        self._set_status(f"**error**: {type(e).__name__}: {e}")

    # ------------------------------------------------------------------ events

    def _on_connect(self, client) -> None:
        """Put a new viewer at the home camera (the capture view facing the objects), then
        render its first composite."""
        t0 = time.perf_counter()
        deadline = time.time() + 10.0
        while client.camera.update_timestamp == 0.0 and time.time() < deadline:
            time.sleep(0.05)                 # its camera state arrives after the connect
        if client.camera.update_timestamp == 0.0:
            return
        p, q, fov = camera_pose_cv(self.home)
        fwd = wxyz_rotation(q)[:, 2]
        dist = float(np.linalg.norm(np.mean([np.add(*self.session.bounds(n)) / 2
                                             for n in self.session.names], 0) - p))
        with client.atomic():
            client.camera.up_direction = (0.0, 0.0, 1.0)
            client.camera.position = p
            client.camera.look_at = p + fwd * max(dist, 1e-6)
            client.camera.fov = fov
        client.camera.on_update(partial(self._on_camera, client))
        self.worker.submit("render", partial(self._render, client, "viewer connected", t0))

    def _on_camera(self, client, _camera) -> None:
        if not self.follow.value:
            return
        self.worker.submit("render", partial(self._render_when_rested, client))

    def _on_gizmo(self, name: str, event) -> None:
        """Drag: the GUI position follows; release: the move is queued."""
        g = self.gizmos[name]
        if event.phase == "update":
            self.positions[name].value = tuple(float(v) for v in g.position)
        elif event.phase == "end":
            t0 = time.perf_counter()
            m = self._matrix(name, g.position, g.wxyz)
            self.positions[name].value = tuple(float(v) for v in g.position)
            self.worker.submit(f"move {name}", partial(self._move, name, m, t0,
                                                       getattr(event, "client", None)))

    def _on_apply(self, name: str, event) -> None:
        """The position typed in the GUI: the gizmo goes there and the move is queued."""
        t0 = time.perf_counter()
        g = self.gizmos[name]
        g.position = tuple(float(v) for v in self.positions[name].value)
        m = self._matrix(name, g.position, g.wxyz)
        self.worker.submit(f"move {name}", partial(self._move, name, m, t0,
                                                   getattr(event, "client", None)))

    def _matrix(self, name: str, position, wxyz) -> np.ndarray:
        m = np.eye(4)
        m[:3, :3] = self.session.world[name].scale * wxyz_rotation(wxyz)
        m[:3, 3] = np.asarray(position, np.float64)
        return m

    # ------------------------------------------------------------------ work (worker thread)

    def camera(self, client, res: int) -> dict:
        """The camera of ``client`` (None: the first viewer connected, else the home
        camera) at ``res`` × ``res`` px (its vertical field of view)."""
        if client is None:
            clients = list(self.server.get_clients().values())
            client = clients[0] if clients else None
        if client is None or client.camera.update_timestamp == 0.0:
            return self.home if self.home["width"] == res else \
                self.session.home_camera(res)
        c = client.camera
        return viewer_camera(c.position, c.wxyz, c.fov, res, res)

    def _move(self, name: str, matrix, t0: float, client) -> None:
        self._set_status(f"re-running the edit for **{name}** ...")
        try:
            e = self.session.move(name, matrix)
        except BaseException:                    # the gizmo goes back to where the object is
            sim = self.session.world[name]
            self.gizmos[name].position = tuple(sim.translation)
            self.gizmos[name].wxyz = tuple(rotation_wxyz(sim.rotation))
            self.positions[name].value = tuple(float(v) for v in sim.translation)
            raise
        self._render(client, f"moved {name}", t0, edit=e)

    def _render_when_rested(self, client) -> None:
        end = time.time() + 10 * CAMERA_SETTLE_S          # a camera that never rests: render
        while time.time() - client.camera.update_timestamp < CAMERA_SETTLE_S and \
                time.time() < end:
            time.sleep(0.05)
        self._render(client, "camera", time.perf_counter())

    def _render(self, client, why: str, t0: float, edit: dict | None = None) -> None:
        cam = self.camera(client, self.cfg.res)
        t = time.perf_counter()
        img = self.session.render(cam, self.variant.value)
        t_render = time.perf_counter() - t
        self.frames += 1
        write_png8(self.out / "preview.png", img)
        self.image.image = (img * 255 + 0.5).astype(np.uint8)
        total = time.perf_counter() - t0
        rec = {"frame": self.frames, "why": why, "variant": self.variant.value,
               "res": [cam["width"], cam["height"]], "render_s": t_render, "total_s": total}
        text = f"frame {self.frames} ({why}, {self.variant.value}, {cam['width']}²): " \
               f"render {t_render:.2f} s"
        if edit is not None:
            rec.update(edit_s=edit["seconds"], lighting_s=edit["lighting"],
                       traced=edit["traced"], reused=edit["reused"], culled=edit["culled"])
            self.last_move = (f"last move (frame {self.frames}): **{edit['name']}** moved, edit "
                              f"{edit['seconds']:.2f} s (lighting {edit['lighting']:.2f} s; "
                              f"pairs traced {len(edit['traced'])}, reused "
                              f"{len(edit['reused'])}) + render {t_render:.2f} s = "
                              f"**{total:.2f} s** from release")
        self._set_status(text)
        self._log(rec)

    def _render_full(self, client) -> None:
        t = time.perf_counter()
        width = self.cfg.full_res or max(self.session.home_camera()["width"], self.cfg.res)
        cam = self.camera(client, width)
        variant = self.variant.value
        img = self.session.render(cam, variant, rays=self.cfg.full_rays)
        k = len(list(self.out.glob(f"full_{variant}_*.png")))
        path = self.out / f"full_{variant}_{k:03d}.png"
        write_png8(path, img)
        dt = time.perf_counter() - t
        self._set_status(f"full size {width}² ({variant}) in {dt:.2f} s: `{path}`")
        self._log({"full": str(path), "variant": variant, "res": [width, width], "total_s": dt})

    def _save(self) -> None:
        p = self.session.save()
        self._set_status(f"saved the placement of {len(self.session.names)} object(s) to `{p}`")
        self._log({"saved": str(p)})

    def _log(self, rec: dict) -> None:
        with open(self.out / "log.jsonl", "a") as f:
            f.write(json.dumps(rec) + "\n")

    # ------------------------------------------------------------------ lifetime

    def wait_idle(self, timeout: float = 600.0) -> bool:
        """True once no job is waiting or running (False after ``timeout`` seconds)."""
        end = time.time() + timeout
        while time.time() < end:
            if self.worker.idle():
                return True
            time.sleep(0.05)
        return False

    def stop(self) -> None:
        self.worker.stop()
        self.server.stop()


def serve(session: ViewSession, say: Callable = print) -> int:
    """Run the viewer until interrupted (Ctrl-C, SIGTERM); returns 0."""
    import signal
    app = ViewerApp(session, say)
    host = session.cfg.host
    say(f"comgs view: http://{'localhost' if host in ('0.0.0.0', '127.0.0.1') else host}:"
        f"{app.port}  (Ctrl-C to stop)")
    done = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: done.set())
    try:
        while not done.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    app.stop()
    return 0

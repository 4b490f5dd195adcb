"""The editor's web layer on viser: the scene, the gizmos and the GUI panel.

It only calls the :class:`~splatdeform.editor.controller.EditorController`: every selector edit,
fit, pose change and save is a controller action; this module turns results into viewer buffers.
Everything shown is in *local* coordinates (model coordinates minus ``controller.origin``).
Pose changes from gizmo drags are coalesced: a worker thread always applies the latest pose, so a
fast drag never queues stale frames.
"""

from __future__ import annotations

import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from splatdeform.geometry import quaternion_to_matrix

from ..errors import ConfigError, SplatdeformError
from . import view
from .controller import EditorController, Frame
from .foreground import serve_until, stop_on_signals
from .security import (
    HostRule,
    SaveFolder,
    default_save_folder,
    exposure_warning,
    guarded_viser,
    new_token,
)

ROLE_COLORS = {"fixed": (50, 110, 255), "handle": (255, 120, 30)}


def _rotation_to(normal: np.ndarray) -> np.ndarray:
    """(4,) wxyz quaternion rotating +z onto ``normal`` (3,)."""
    z = np.array([0.0, 0.0, 1.0])
    n = np.asarray(normal, float) / max(np.linalg.norm(normal), 1e-300)
    axis = np.cross(z, n)
    s, c = np.linalg.norm(axis), float(z @ n)
    if s < 1e-12:
        return np.array([1.0, 0, 0, 0]) if c > 0 else np.array([0.0, 1, 0, 0])
    half = np.arctan2(s, c) / 2
    return np.concatenate([[np.cos(half)], np.sin(half) * axis / s])


def pose_matrix(origin: np.ndarray, start: np.ndarray, position: np.ndarray,
                wxyz: np.ndarray) -> np.ndarray:
    """4x4 model-space map of a gizmo moved from local ``start`` (3,) (identity rotation) to
    local ``position`` (3,) with rotation ``wxyz`` (4,): rotate about the start, then move."""
    r = quaternion_to_matrix(np.asarray(wxyz, float)[None])[0]
    pivot = origin + np.asarray(start, float)
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = origin + np.asarray(position, float) - r @ pivot
    return m


class EditorApp:
    """The viser scene and GUI over one controller."""

    def __init__(self, controller: EditorController, server: Any,
                 save_folder: SaveFolder | None = None) -> None:
        self.ed = controller
        self.server = server
        self.save_folder = save_folder or default_save_folder(controller)
        self.lock = threading.RLock()
        self.model = controller.model
        self.up = view.up_direction(self.model)
        self.colors = view.base_colors(self.model)
        self.kind = ("splats" if self.model.gaussians is not None
                     else "mesh" if self.model.n_faces else "points")
        self._selector_nodes: list[Any] = []
        self._pose_gizmos: list[Any] = []
        self._pose_base: list[tuple[np.ndarray, np.ndarray]] = []
        self._pending: tuple[int, np.ndarray] | None = None
        self._wake = threading.Event()
        self._closing = False
        self.frames = 0
        self.last_ms = 0.0
        self._build_scene()
        self._build_gui()
        self.refresh_regions()
        self._worker = threading.Thread(target=self._pose_worker, name="editor-pose", daemon=True)
        self._worker.start()

    # ---- scene -------------------------------------------------------------------------
    def _build_scene(self) -> None:
        s, m = self.server.scene, self.model
        # The viewer is +y up; a y-down model (3DGS) hangs under a frame turned 180 degrees
        # about x. Gizmo poses are reported in that frame, i.e. in local model coordinates.
        s.set_up_direction("+y")
        s.add_frame("/world", show_axes=False,
                    wxyz=(0.0, 1.0, 0.0, 0.0) if self.up == "-y" else (1.0, 0.0, 0.0, 0.0))
        diag = max(m.diagonal(), 1e-9)
        self.server.initial_camera.position = (0.55 * diag, 0.35 * diag, 0.9 * diag)
        self.server.initial_camera.look_at = (0.0, 0.0, 0.0)
        frame = self.ed.base_frame()
        self.labels = self.ed.labels()
        self._tinted = view.tinted(self.colors, self.labels)
        self._which = 0
        if self.kind == "splats":
            self._rgba = view.splat_rgba(m, self._tinted)
            self.node = s.add_gaussian_splats(
                "/world/model/splats", centers=frame.positions, covariances=frame.covariances,
                rgbs=self._rgba[:, :3], opacities=self._rgba[:, 3:4])
        else:
            if self.kind == "mesh":
                self.mesh = s.add_mesh_simple("/world/model/mesh", frame.positions,
                                              self.model.faces.astype(np.uint32),
                                              color=(200, 200, 200), side="double")
            self.node = s.add_point_cloud(
                "/world/model/points", frame.positions,
                view.shaded(self._tinted, frame.normals, self.up),
                point_size=view.point_size(m) * (0.5 if self.kind == "mesh" else 1.0),
                point_shape="circle", precision="float32", point_shading="flat")
        self.reset_buffers(frame)

    def reset_buffers(self, frame: Frame) -> None:
        """Both viewer double buffers from a whole-model frame, in viewer order: the points a
        pose moves (non-fixed, ``frame.index`` of later frames) first, so a pose change writes
        one contiguous block instead of scattering. Called after each fit (the order changes;
        rows that became fixed show the undeformed points again)."""
        active = self.ed.moving_points()
        n = self.model.n_points
        if active is None:
            self._perm, self._n_act = np.arange(n), n
        else:
            fixed = np.ones(n, dtype=bool)
            fixed[active] = False
            self._perm, self._n_act = np.concatenate([active, np.flatnonzero(fixed)]), len(active)
        self._shown_fit = None if self._n_act == n else self.ed.deformation
        perm = self._perm
        self._tinted = view.tinted(self.colors, self.labels)[perm]
        self.cur_normals = None if frame.normals is None else frame.normals[perm]
        if self.kind == "splats":
            self._packed = np.ascontiguousarray(self._rgba).view(np.uint32)[perm, 0]
            buf = view.splat_rows(frame.positions[perm], frame.cov6[perm], self._packed)
            self._bufs = [buf, buf.copy()]
        else:
            colors = view.shaded(self._tinted, self.cur_normals, self.up)
            self._bufs = [frame.positions[perm], frame.positions[perm]]
            self._colors = [colors, colors.copy()]
            if self.kind == "mesh":
                inverse = np.empty(n, dtype=np.int64)
                inverse[perm] = np.arange(n)
                self.mesh.faces = inverse[self.model.faces].astype(np.uint32)
        self._hand_over()

    def shown(self) -> tuple[np.ndarray, np.ndarray]:
        """What the viewer holds, in model order: positions (N, 3) float32 (local) and colours
        (N, 3) uint8 (splats: RGBA packed (N,) uint32)."""
        w, n = self._which, self.model.n_points
        pos = np.empty((n, 3), np.float32)
        if self.kind == "splats":
            pos[self._perm] = self._bufs[w].view(np.float32)[:, 0:3]
            col = np.empty(n, np.uint32)
            col[self._perm] = self._bufs[w][:, 7]
            return pos, col
        pos[self._perm] = self._bufs[w]
        col = np.empty((n, 3), np.uint8)
        col[self._perm] = self._colors[w]
        return pos, col

    def _hand_over(self) -> None:
        """Give viser the current double buffer (it keeps a reference: we write the other)."""
        w = self._which
        if self.kind == "splats":
            self.node.buffer = self._bufs[w]
            return
        if self.kind == "mesh":
            self.mesh.vertices = self._bufs[w]
        self.node.points = self._bufs[w]
        self.node.colors = self._colors[w]

    def show_frame(self, frame: Frame) -> None:
        """Hand a frame's buffers to the viewer (the end of the measured pose path)."""
        if frame.index is None:
            self.reset_buffers(frame)
            return
        if len(frame.index) != self._n_act:
            raise RuntimeError("frame: rows do not match the viewer's order; refit")
        rows = slice(0, self._n_act)
        self._which ^= 1
        w = self._which
        if self.kind == "splats":
            self._bufs[w][rows] = view.splat_rows(frame.positions, frame.cov6,
                                                  self._packed[rows])
        else:
            self._bufs[w][rows] = frame.positions
            if frame.normals is not None:
                self.cur_normals[rows] = frame.normals
                self._colors[w][rows] = view.shaded(self._tinted[rows], frame.normals, self.up)
        self._hand_over()

    def refresh_regions(self) -> None:
        """Recolour by region and update counts, problems and the stale flag."""
        with self.lock:
            self.labels = self.ed.labels()
            tinted = view.tinted(self.colors, self.labels)
            self._tinted = tinted[self._perm]
            self._which ^= 1
            if self.kind == "splats":
                self._rgba = view.splat_rgba(self.model, tinted)
                self._packed = np.ascontiguousarray(self._rgba).view(np.uint32)[self._perm, 0]
                # new arrays: viser keeps the one it was given and compares against it
                self._bufs = [buf.copy() for buf in self._bufs]
                for buf in self._bufs:
                    buf[:, 7] = self._packed
            else:
                colors = view.shaded(self._tinted, self.cur_normals, self.up)
                self._colors = [colors, colors.copy()]
            self._hand_over()
            c = self.ed.counts()
            problem = self.ed.problem()
            fit = "none yet" if self.ed.deformation is None else (
                "**stale** (regions changed: fit again)" if self.ed.stale else "current")
            lines = [f"fixed **{c['fixed']:,}** · handle **{c['handle']:,}** · "
                     f"free **{c['free']:,}** of {self.model.n_points:,}", f"fit: {fit}"]
            if problem:
                lines.append(f"⚠ {problem}")
            self.counts_md.content = "  \n".join(lines)

    # ---- selectors ---------------------------------------------------------------------
    def _selector_entries(self) -> dict[str, tuple[str, int, int]]:
        """GUI label -> (role, handle, index) of every selector."""
        out = {}
        for i, sel in enumerate(self.ed.fixed):
            out[f"fixed {i} ({type(sel).__name__.lower()})"] = ("fixed", 0, i)
        many = len(self.ed.handles) > 1
        for h, state in enumerate(self.ed.handles):
            for i, sel in enumerate(state.selectors):
                name = f"handle {h}.{i}" if many else f"handle {i}"
                out[f"{name} ({type(sel).__name__.lower()})"] = ("handle", h, i)
        return out

    def rebuild_selectors(self) -> None:
        """One gizmo + outline per box / sphere / plane selector."""
        s = self.server.scene
        for node in self._selector_nodes:
            node.remove()
        self._selector_nodes = []
        entries = self._selector_entries()
        for role, h, i in entries.values():
            shape = self.ed.shape(role, i, handle=h)
            if shape.kind == "other":
                continue
            name = f"/world/selectors/{role}{h}_{i}"
            wxyz = _rotation_to(shape.normal) if shape.kind == "plane" else (1.0, 0, 0, 0)
            size = float(max(self.model.diagonal(), 1e-9))
            gizmo = s.add_transform_controls(
                name, scale=0.15 * size, position=shape.center - self.ed.origin, wxyz=wxyz,
                disable_rotations=shape.kind != "plane", depth_test=False)
            color = ROLE_COLORS[role]
            if shape.kind == "box":
                outline = s.add_box(f"{name}/outline", color=color,
                                    dimensions=tuple(np.maximum(shape.size, 1e-9)), wireframe=True)
            elif shape.kind == "sphere":
                outline = s.add_icosphere(f"{name}/outline", radius=float(shape.size[0]),
                                          color=color, wireframe=True, subdivisions=2)
            else:
                outline = s.add_box(f"{name}/outline", color=color,
                                    dimensions=(0.8 * size, 0.8 * size, 1e-3 * size),
                                    opacity=0.25)
            gizmo.on_update(self._selector_moved(role, h, i, shape.kind))
            self._selector_nodes += [outline, gizmo]
        self.selected.options = tuple(entries) or ("(none)",)
        self.active.options = tuple(f"handle {h}" for h in range(len(self.ed.handles)))
        self._on_selected()

    def _selector_moved(self, role: str, handle: int, index: int, kind: str):
        def callback(event: Any) -> None:
            g = event.target
            with self.lock:
                normal = None
                if kind == "plane":
                    normal = quaternion_to_matrix(np.asarray(g.wxyz)[None])[0][:, 2]
                self.ed.move_selector(role, index, center=np.asarray(g.position) + self.ed.origin,
                                      normal=normal, handle=handle)
            self.refresh_regions()
        return callback

    def _selected_entry(self) -> tuple[str, int, int] | None:
        return self._selector_entries().get(self.selected.value)

    def _on_selected(self, *_: Any) -> None:
        entry = self._selected_entry()
        if entry is None:
            return
        role, h, i = entry
        shape = self.ed.shape(role, i, handle=h)
        self._syncing = True
        try:
            self.size_input.value = tuple(float(v) for v in shape.size)
        finally:
            self._syncing = False

    def _on_size(self, *_: Any) -> None:
        entry = self._selected_entry()
        if entry is None or getattr(self, "_syncing", False):
            return
        size = np.abs(np.asarray(self.size_input.value, float))
        role, h, i = entry
        with self.lock:
            try:
                if self.ed.shape(role, i, handle=h).kind == "sphere":
                    size = np.full(3, size.max())
                self.ed.move_selector(role, i, size=size, handle=h)
            except SplatdeformError as exc:
                self.status(str(exc))
                return
        self.rebuild_selectors()
        self.refresh_regions()

    def _active_handle(self) -> int:
        return int(str(self.active.value).split()[-1])

    def _add(self, role: str, kind: str) -> None:
        with self.lock:
            self.ed.add_selector(role, kind, handle=self._active_handle())
        self.rebuild_selectors()
        self.refresh_regions()

    def _remove(self, *_: Any) -> None:
        entry = self._selected_entry()
        if entry is None:
            return
        role, h, i = entry
        with self.lock:
            self.ed.remove_selector(role, i, handle=h)
        self.rebuild_selectors()
        self.refresh_regions()

    def _new_handle(self, *_: Any) -> None:
        with self.lock:
            h = self.ed.add_handle()
        self.rebuild_selectors()
        self.active.value = f"handle {h}"
        self.refresh_regions()

    # ---- fit and pose ------------------------------------------------------------------
    def _fit(self, *_: Any) -> None:
        self.fit_button.disabled = True
        self.progress.visible = True
        self.progress.animated = True

        def report(stage: str, fraction: float) -> None:
            self.progress.value = 100.0 * fraction
            self.fit_md.content = f"fitting: {stage} …"

        try:
            with self.lock:
                stats = self.ed.fit(report)
                self.reset_buffers(self.ed.set_pose(self.ed.handles[0].matrix))
            self.fit_md.content = (
                f"centers **{stats['centers']}** · constraints {stats['constraints']:,} "
                f"(kept {stats.get('kept', stats['constraints']):,}, {stats.get('method', '')}) · "
                f"converged {str(stats['converged']).lower()}  \n"
                f"rings {stats.get('rings_s', 0):.2f} s · fit {stats.get('fit_s', 0):.2f} s · "
                f"basis {stats.get('basis_s', 0):.2f} s")
            self._build_pose_gizmos()
        except SplatdeformError as exc:
            self.fit_md.content = f"⚠ {exc}"
        finally:
            self.progress.animated = False
            self.progress.visible = False
            self.fit_button.disabled = False
        self.refresh_regions()

    def _build_pose_gizmos(self) -> None:
        for g in self._pose_gizmos:
            g.remove()
        self._pose_gizmos, self._pose_base = [], []
        for h, state in enumerate(self.ed.handles):
            start = self.ed.handle_pivot(h) - self.ed.origin
            g = self.server.scene.add_transform_controls(
                f"/world/handles/pose{h}", scale=0.25 * max(self.model.diagonal(), 1e-9),
                position=start, depth_test=False)
            self._pose_base.append((start, state.matrix.copy()))
            g.on_update(self._pose_moved(h))
            self._pose_gizmos.append(g)

    def _pose_moved(self, h: int):
        def callback(event: Any) -> None:
            g = event.target
            start, base = self._pose_base[h]
            delta = pose_matrix(self.ed.origin, start, np.asarray(g.position),
                                np.asarray(g.wxyz))
            self.request_pose(h, delta @ base)
        return callback

    def request_pose(self, handle: int, matrix: np.ndarray) -> None:
        """Queue a pose change (the latest one wins) for the worker thread."""
        self._pending = (handle, matrix)
        self._wake.set()

    def apply_pose(self, handle: int, matrix: np.ndarray) -> float:
        """Pose received -> new buffers handed to the viewer; returns the seconds it took."""
        t0 = time.perf_counter()
        with self.lock:
            if self._shown_fit is not self.ed.deformation:  # fitted outside the app
                self.reset_buffers(self.ed.set_pose(matrix, handle))
            self.show_frame(self.ed.set_pose(matrix, handle, full=False))
        return time.perf_counter() - t0

    def _pose_worker(self) -> None:
        while not self._closing:
            self._wake.wait(0.5)
            self._wake.clear()
            pending, self._pending = self._pending, None
            if pending is None:
                continue
            try:
                seconds = self.apply_pose(*pending)
            except SplatdeformError as exc:
                self.status(str(exc))
                continue
            self.frames += 1
            self.last_ms = 1000 * seconds
            self.pose_md.content = f"pose updates {self.frames} · last {self.last_ms:.0f} ms"

    def _reset(self, *_: Any) -> None:
        with self.lock:
            self.ed.reset_pose()
            if not self.ed.stale:
                self.reset_buffers(self.ed.set_pose(np.eye(4)))
                self._build_pose_gizmos()

    # ---- save --------------------------------------------------------------------------
    def save_names(self, model: str, edit_yaml: str, image: str, *,
                   replace: bool = False) -> str:
        """Save under the file names typed in the page, in the save folder. Existing files are
        only replaced with ``replace`` (the user confirmed); inputs never. Returns the status
        line (what was written, what needs confirming, or the error)."""
        try:
            with self.lock:
                paths = self.save_folder.save_targets(model, edit_yaml, image)
                existing = self.save_folder.existing(paths)
                if existing and not replace:
                    self._confirm_pending = (model, edit_yaml, image)
                    return ("exists already: " + ", ".join(p.name for p in existing)
                            + "; press 'replace existing' to overwrite, or change the names")
                self._confirm_pending = None
                result = self.ed.save(*paths[:3])
            return f"wrote {result.model.name}, {result.config.name}, {result.image.name}"
        except SplatdeformError as exc:
            self._confirm_pending = None
            return str(exc)

    def _save(self, *_: Any, replace: bool = False) -> None:
        self.save_button.disabled = True
        try:
            names = (self.out_model.value, self.out_yaml.value, self.out_png.value)
            if replace and self._confirm_pending != names:  # the names changed meanwhile
                replace = False
            self.status(self.save_names(*names, replace=replace))
        finally:
            self.save_button.disabled = False
            self.replace_button.visible = self._confirm_pending is not None

    def status(self, text: str) -> None:
        self.status_md.content = text

    # ---- GUI ---------------------------------------------------------------------------
    def _build_gui(self) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**splatdeform editor** · `{self.ed.model_path.name}` "
                         f"({self.model.kind}, {self.model.n_points:,} points)")
        self.counts_md = gui.add_markdown("")
        with gui.add_folder("Regions"):
            for role in ("fixed", "handle"):
                group = gui.add_button_group(f"add {role}", ("box", "sphere", "plane"))
                group.on_click(lambda e, role=role: self._add(role, e.target.value))
            self.active = gui.add_dropdown("adds to", ("handle 0",))
            gui.add_button("new handle").on_click(self._new_handle)
            self.selected = gui.add_dropdown("selector", ("(none)",))
            self.selected.on_update(self._on_selected)
            self.size_input = gui.add_vector3("size", (0.0, 0.0, 0.0), step=1e-3)
            self.size_input.on_update(self._on_size)
            gui.add_button("remove selector").on_click(self._remove)
        with gui.add_folder("Fit"):
            self.fit_button = gui.add_button("Fit")
            self.fit_button.on_click(self._fit)
            self.progress = gui.add_progress_bar(0.0, visible=False)
            self.fit_md = gui.add_markdown("no fit yet: mark fixed and handle regions, then Fit")
        with gui.add_folder("Handle"):
            gui.add_button("reset pose").on_click(self._reset)
            self.pose_md = gui.add_markdown("drag the handle gizmo after a fit")
        with gui.add_folder("Save"):
            model_p, yaml_p, png_p = self.ed.default_paths()
            gui.add_markdown(f"into `{self.save_folder.root}` (file names only)")
            self.out_model = gui.add_text("model", model_p.name)
            self.out_yaml = gui.add_text("edit YAML", yaml_p.name)
            self.out_png = gui.add_text("before/after", png_p.name)
            self.save_button = gui.add_button("Save")
            self.save_button.on_click(self._save)
            self.replace_button = gui.add_button("replace existing", visible=False)
            self.replace_button.on_click(lambda *_: self._save(replace=True))
            self._confirm_pending = None
        self.status_md = gui.add_markdown("")

    def start(self) -> None:
        """Show the loaded state: selector gizmos, and the pose when a fit is current."""
        self.rebuild_selectors()

    def close(self) -> None:
        self._closing = True
        self._wake.set()


def run(path: str, *, host: str = "127.0.0.1", port: int = 8080,
        ready: threading.Event | None = None, save_dir: str | Path | None = None,
        token: str | None = None, allow_hosts: tuple[str, ...] = ()) -> int:
    """Load MODEL or EDIT.yaml, serve the editor, print its URL (with its access token), block
    until Ctrl-C / SIGTERM. Saves go into ``save_dir`` (default: the opened file's folder).
    Returns 0 (clean shutdown)."""
    import viser

    controller = EditorController.open(path)
    if controller.curve is not None:
        raise ConfigError(f"{path}: curve: the viser viewer edits handles only; open curve "
                          "edits in the page (--viewer page, the default)")
    folder = default_save_folder(controller, save_dir)
    token = token or new_token()
    with stop_on_signals() as stop:
        with guarded_viser(token, HostRule(host, tuple(allow_hosts))):
            server = viser.ViserServer(host=host, port=port, verbose=False)
        app = None
        try:
            app = EditorApp(controller, server, folder)
            app.start()
            shown = "127.0.0.1" if host in ("0.0.0.0", "", "::") else host
            shown = f"[{shown}]" if ":" in shown else shown
            print(f"splatdeform editor: http://{shown}:{server.get_port()}/?token={token}  "
                  f"({controller.model.n_points:,} points; saves into {folder.root}; "
                  "Ctrl-C to stop)", flush=True)
            warning = exposure_warning(host, server.get_port())
            if warning:
                print(warning, file=sys.stderr, flush=True)
            serve_until(stop, ready)
        finally:
            if app is not None:
                app.close()
            server.stop()
    print("splatdeform editor: stopped", flush=True)
    return 0


__all__ = ["EditorApp", "default_save_folder", "pose_matrix", "run"]

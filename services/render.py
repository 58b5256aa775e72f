"""Headless PNG snapshots: OpenGL through EGL (moderngl), no window or display needed.

Works on Mesa's software rasteriser (llvmpipe); Debian packages libegl1,
libegl-mesa0, libgl1-mesa-dri.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

_VERT = """
#version 330
uniform mat4 u_mvp;
in vec3 in_position;
in vec3 in_normal;
out vec3 v_normal;
out vec3 v_world;
void main() {
    v_normal = in_normal;
    v_world = in_position;
    gl_Position = u_mvp * vec4(in_position, 1.0);
}
"""
_FRAG = """
#version 330
uniform vec3 u_color;
uniform vec3 u_eye;
uniform int u_checker;
in vec3 v_normal;
in vec3 v_world;
out vec4 f_color;
void main() {
    vec3 n = normalize(v_normal);
    vec3 view = normalize(u_eye - v_world);
    if (dot(n, view) < 0.0) n = -n;  // two-sided: cloth and open meshes show their inside
    vec3 key = normalize(vec3(0.4, 0.8, 0.6));
    vec3 fill = normalize(vec3(-0.6, 0.3, -0.2));
    float diffuse = max(dot(n, key), 0.0) * 0.75 + max(dot(n, fill), 0.0) * 0.25;
    float rim = pow(1.0 - max(dot(n, view), 0.0), 3.0) * 0.15;
    vec3 base = u_color;
    if (u_checker == 1) {
        float c = mod(floor(v_world.x * 2.0) + floor(v_world.z * 2.0), 2.0);
        base = mix(vec3(0.55), vec3(0.68), c);
        diffuse = 0.9;
        rim = 0.0;
    }
    f_color = vec4(base * (0.25 + diffuse) + rim, 1.0);
}
"""


@dataclass
class Camera:
    eye: np.ndarray
    target: np.ndarray
    fov_deg: float = 35.0
    near: float = 0.05
    far: float = 50.0

    def matrix(self, aspect: float) -> np.ndarray:
        f = self.target - self.eye
        f = f / np.linalg.norm(f)
        up = np.array([0.0, 1.0, 0.0])
        s = np.cross(f, up)
        s /= np.linalg.norm(s)
        u = np.cross(s, f)
        view = np.eye(4)
        view[0, :3], view[1, :3], view[2, :3] = s, u, -f
        view[:3, 3] = -view[:3, :3] @ self.eye
        t = 1.0 / np.tan(np.deg2rad(self.fov_deg) / 2)
        proj = np.zeros((4, 4))
        proj[0, 0] = t / aspect
        proj[1, 1] = t
        proj[2, 2] = (self.far + self.near) / (self.near - self.far)
        proj[2, 3] = 2 * self.far * self.near / (self.near - self.far)
        proj[3, 2] = -1.0
        return proj @ view


def orbit_camera(target: np.ndarray, azimuth_deg: float, distance: float = 3.2, height: float = 0.15) -> Camera:
    """A camera around a target; azimuth 0 looks at the character's front (it faces +Z)."""
    a = np.deg2rad(azimuth_deg)
    eye = target + np.array([distance * np.sin(a), height, distance * np.cos(a)])
    return Camera(eye=eye, target=np.asarray(target, dtype=float))


@dataclass
class MeshDraw:
    vertices: np.ndarray  # (n, 3)
    triangles: np.ndarray  # (m, 3)
    normals: np.ndarray  # (n, 3)
    color: tuple[float, float, float] = (0.85, 0.68, 0.58)


class Renderer:
    """Offscreen renderer; supersamples and downsizes for smooth edges."""

    def __init__(self, width: int = 640, height: int = 800, supersample: int = 2):
        import moderngl

        self.width, self.height, self.ss = width, height, supersample
        try:
            self.ctx = moderngl.create_standalone_context(backend="egl")
        except Exception as exc:  # pragma: no cover - depends on the machine's GL stack
            raise RuntimeError(
                "cannot create a headless OpenGL context through EGL; install Debian packages "
                "libegl1 libegl-mesa0 libgl1-mesa-dri"
            ) from exc
        self.prog = self.ctx.program(vertex_shader=_VERT, fragment_shader=_FRAG)
        w, h = width * supersample, height * supersample
        self.fbo = self.ctx.simple_framebuffer((w, h), components=4)
        self.ctx.enable(self.ctx.DEPTH_TEST)
        floor = np.array([[-20, 0, -20], [20, 0, -20], [20, 0, 20], [-20, 0, 20]], dtype=np.float32)
        self._floor = MeshDraw(floor, np.array([[0, 2, 1], [0, 3, 2]]), np.tile([0, 1, 0], (4, 1)))

    def _draw(self, mesh: MeshDraw, checker: bool) -> None:
        tri = np.ascontiguousarray(mesh.triangles, dtype=np.int32)
        used = np.unique(tri)
        data = np.hstack([mesh.vertices[used], mesh.normals[used]]).astype(np.float32)
        remap = np.zeros(len(mesh.vertices), dtype=np.int32)
        remap[used] = np.arange(len(used), dtype=np.int32)
        vbo = self.ctx.buffer(data.tobytes())
        ibo = self.ctx.buffer(remap[tri].astype(np.int32).tobytes())
        vao = self.ctx.vertex_array(self.prog, [(vbo, "3f 3f", "in_position", "in_normal")], ibo)
        self.prog["u_color"].value = tuple(mesh.color)
        self.prog["u_checker"].value = 1 if checker else 0
        vao.render()
        vao.release()
        vbo.release()
        ibo.release()

    def render(self, meshes: list[MeshDraw], camera: Camera, floor: bool = True) -> np.ndarray:
        """RGB image (height, width, 3) uint8."""
        from PIL import Image

        self.fbo.use()
        self.fbo.clear(0.93, 0.94, 0.96, 1.0)
        mvp = camera.matrix(self.width / self.height)
        self.prog["u_mvp"].write(mvp.T.astype(np.float32).tobytes())
        self.prog["u_eye"].value = tuple(float(x) for x in camera.eye)
        if floor:
            self._draw(self._floor, checker=True)
        for mesh in meshes:
            self._draw(mesh, checker=False)
        raw = self.fbo.read(components=3)
        img = Image.frombytes("RGB", self.fbo.size, raw).transpose(Image.Transpose.FLIP_TOP_BOTTOM)
        if self.ss > 1:
            img = img.resize((self.width, self.height), Image.Resampling.LANCZOS)
        return np.asarray(img)

    def release(self) -> None:
        self.ctx.release()


def save_png(path: str | Path, image: np.ndarray) -> None:
    from PIL import Image

    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)


def contact_sheet(images: list[np.ndarray], columns: int) -> np.ndarray:
    """Tile same-sized images into one, at most `columns` per row (fewer images: one row of them)."""
    h, w, _ = images[0].shape
    columns = max(1, min(columns, len(images)))
    rows = (len(images) + columns - 1) // columns
    sheet = np.full((rows * h, columns * w, 3), 255, dtype=np.uint8)
    for k, img in enumerate(images):
        r, c = divmod(k, columns)
        sheet[r * h:(r + 1) * h, c * w:(c + 1) * w] = img
    return sheet

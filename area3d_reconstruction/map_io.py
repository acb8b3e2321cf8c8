"""The reconstruction's volume in a map file (`area3d_msgs_py/mapfile.py`, content
"reconstruction") and its mesh as PLY.

The file holds the TSDF volume's active blocks (`TsdfFusion.state`: block coordinates, each
voxel's signed distance, weight and colour), the stamps of the frames integrated (a frame is
integrated once, after a load too) and, in the header, the volume's parameters and region: a
file of another voxel length, truncation or region is refused. docs/map_format.md lists every
entry.
"""

from __future__ import annotations

from dataclasses import asdict, fields
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from area3d_eval.open3d_loader import import_open3d
from area3d_eval.reconstruct import BLOCK_RESOLUTION, TsdfFusion, TsdfParams
from area3d_msgs_py import mapfile
from area3d_msgs_py.errors import InputError

CONTENT = "reconstruction"
# each voxel's arrays: (name, channels, the values `TsdfFusion` writes: docs/map_format.md, with
# room for a float's rounding of a weighted mean at the top of the range)
VOXEL_ARRAYS = (
    ("tsdf", 1, (-1.0001, 1.0001)),  # signed distance / truncation
    ("weight", 1, (0.0, None)),  # summed confidence
    ("color", 3, (0.0, 255.01)),
)


def volume_header(fusion: TsdfFusion) -> dict:
    """What a file must match to be loaded into `fusion`: its TSDF parameters and region."""
    return {
        **{f"tsdf_{k}": v for k, v in asdict(fusion.params).items()},
        "roi_min": None if fusion.roi_lo is None else fusion.roi_lo.tolist(),
        "roi_max": None if fusion.roi_hi is None else fusion.roi_hi.tolist(),
    }


def save(
    fusion: TsdfFusion, stamps: list[int], path, world_frame: str | None = None
) -> tuple[Path, int]:
    """Write the volume (in `world_frame`) and its integrated frames' stamps to `path`
    atomically."""
    arrays = {**fusion.state(), "stamps": np.asarray(stamps, np.int64)}
    header = {
        **volume_header(fusion),
        "frames": fusion.num_frames,
        "blocks": int(arrays["block_keys"].shape[0]),
    }
    return mapfile.write_map(path, CONTENT, header, arrays, world_frame)


def read(fusion: TsdfFusion, path, world_frame: str | None = None) -> mapfile.MapFile:
    """Read a reconstruction file for `fusion`, checked whole (parameters, region, frame,
    arrays)."""
    return check(fusion, mapfile.read_map(path, CONTENT, world_frame))


def check(fusion: TsdfFusion, loaded: mapfile.MapFile) -> mapfile.MapFile:
    """Refuse a read reconstruction file that `fusion` could not have written (`read`)."""
    for key, running in volume_header(fusion).items():
        if key not in loaded.header:
            raise InputError(f"{loaded.path}: {key}", "missing", "a reconstruction file's header")
        saved = loaded.header[key]
        if running is None or saved is None:
            if running != saved:
                raise InputError(
                    f"{loaded.path}: {key}", saved, f"{running} (the running volume's)"
                )
            continue
        mapfile.check_same(loaded.path, key, saved, running)
    loaded.require({"frames": "count", "blocks": "count"})
    blocks = loaded.header["blocks"]
    if blocks and not loaded.header["frames"]:
        raise InputError(
            f"{loaded.path}: frames", 0, f"at least 1 frame integrated into its {blocks} blocks"
        )
    _check_blocks(fusion, loaded, loaded.array("block_keys", np.int32, (blocks, 3)))
    r = BLOCK_RESOLUTION
    for name, channels, bounds in VOXEL_ARRAYS:
        loaded.array(name, np.float32, (blocks, r, r, r, channels), finite=True, bounds=bounds)
    # one stamp a frame integrated (a frame is integrated once, after a load too)
    loaded.array("stamps", np.int64, (loaded.header["frames"],))
    return loaded


def _check_blocks(fusion: TsdfFusion, loaded: mapfile.MapFile, keys: np.ndarray) -> None:
    """Refuse block coordinates that repeat, or that lie off the region (grown by its margin,
    the truncation band and a block): a volume the running one could not have integrated."""
    if np.unique(keys, axis=0).shape[0] != keys.shape[0]:
        raise InputError(f"{loaded.path}: array 'block_keys'", "repeated blocks", "each once")
    if fusion.roi_lo is None or keys.shape[0] == 0:
        return
    p = fusion.params
    size = p.voxel_length * BLOCK_RESOLUTION
    grow = p.roi_margin + p.sdf_trunc + size
    lo, hi = keys * size, (keys + 1) * size  # each block's extent, metres
    off = np.any((hi < fusion.roi_lo - grow) | (lo > fusion.roi_hi + grow), axis=1)
    if off.any():
        raise InputError(
            f"{loaded.path}: array 'block_keys'",
            f"{int(off.sum())} blocks off the region (the first at {lo[off][0].tolist()} m)",
            f"blocks within {fusion.roi_lo.tolist()} .. {fusion.roi_hi.tolist()} grown by "
            f"{grow:g} m",
        )


def mesh_of_file(path) -> Any:
    """The mesh (open3d TriangleMesh) of a saved volume, without a running node: a volume of the
    file's own parameters and region, the file read once, checked whole and restored into it."""
    loaded = mapfile.read_map(path, CONTENT)
    header = loaded.header
    values = {}
    for field in fields(TsdfParams):
        key, value = f"tsdf_{field.name}", header.get(f"tsdf_{field.name}")
        kind = int if field.name == "depth_stride" else float
        if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
            raise InputError(f"{mapfile.resolve(path)}: {key}", value, "a number > 0")
        values[field.name] = kind(value)
    region = [header.get("roi_min"), header.get("roi_max")]
    if region != [None, None] and not all(
        isinstance(c, list) and len(c) == 3 and all(isinstance(v, int | float) for v in c)
        for c in region
    ):
        raise InputError(f"{mapfile.resolve(path)}: roi_min, roi_max", region, "[x, y, z] each")
    lo, hi = (None, None) if region == [None, None] else (np.asarray(c, float) for c in region)
    fusion = TsdfFusion(TsdfParams(**values), lo, hi)
    restore(fusion, check(fusion, loaded))
    return fusion.extract_mesh()


def restore(fusion: TsdfFusion, loaded: mapfile.MapFile) -> list[int]:
    """Put the file's volume in `fusion`; the stamps of its integrated frames."""
    fusion.restore(loaded.arrays, int(loaded.header["frames"]))
    return [int(s) for s in loaded.arrays["stamps"]]


def export_mesh(mesh, path) -> tuple[Path, int]:
    """Write an open3d TriangleMesh as binary PLY (vertex normals and colours) to `path`
    atomically (`mapfile.write_file`). The PLY is made in memory (trimesh) and written by this
    process's own file handle: open3d's writer leaves its file open when its last write fails
    (a full disk), which kept the space of the refused file taken until the node stopped."""
    o3d = import_open3d()
    if mapfile.resolve(path).suffix.lower() != ".ply":
        raise InputError("path", str(mapfile.resolve(path)), "a file name ending in .ply")

    if len(mesh.triangles) == 0:
        raise InputError(
            "mesh",
            "0 triangles",
            "a reconstruction with a surface "
            "(no frame integrated yet, or none since a reset or the load of an empty map)",
        )
    data = ply_bytes(mesh)

    def write(tmp: Path) -> None:
        with tmp.open("wb") as out:
            out.write(data)
        # read back whole: what a reader gets is what was meant
        back = o3d.io.read_triangle_mesh(str(tmp))
        wrote = (len(back.vertices), len(back.triangles))
        if wrote != (len(mesh.vertices), len(mesh.triangles)):
            raise OSError(
                f"the mesh written to {tmp} reads back as {wrote[0]} vertices and {wrote[1]} "
                f"triangles, not {len(mesh.vertices)} and {len(mesh.triangles)}"
            )

    return mapfile.write_file(path, write, suffix=".ply")


def ply_bytes(mesh) -> bytes:
    """An open3d TriangleMesh as a binary little-endian PLY: float32 vertices (0.1 um at 1 m),
    their normals and 8-bit colours with alpha (when the mesh has them), triangles."""
    normals = np.asarray(mesh.vertex_normals) if mesh.has_vertex_normals() else None
    colours = None
    if mesh.has_vertex_colors():
        colours = np.round(np.clip(np.asarray(mesh.vertex_colors), 0.0, 1.0) * 255.0)
        colours = colours.astype(np.uint8)
    out = trimesh.Trimesh(
        vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.triangles),
        vertex_normals=normals, vertex_colors=colours, process=False,
    )  # fmt: skip
    return trimesh.exchange.ply.export_ply(
        out, encoding="binary", vertex_normal=normals is not None, include_attributes=False
    )

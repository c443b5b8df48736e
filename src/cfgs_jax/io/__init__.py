"""File I/O: 3DGS PLY, fused models (ours and the reference layout), COLMAP datasets, images, run
folders."""

from cfgs_jax.io.atomic import atomic_directory, atomic_file, ensure_writable_dir
from cfgs_jax.io.colmap import Scene, read_colmap
from cfgs_jax.io.fused import read_fused, write_fused
from cfgs_jax.io.images import read_image, write_image
from cfgs_jax.io.ply import read_ply, write_ply
from cfgs_jax.io.run_dir import RunDir

__all__ = [
    "RunDir",
    "Scene",
    "atomic_directory",
    "atomic_file",
    "ensure_writable_dir",
    "read_colmap",
    "read_fused",
    "read_image",
    "read_ply",
    "write_fused",
    "write_image",
    "write_ply",
]

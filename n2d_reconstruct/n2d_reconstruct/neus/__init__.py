"""NeuS with a multi-resolution hash grid in pure PyTorch: an SDF and radiance field of the object from
masked, posed views (CPU first, CUDA when present).

    field = train_neus(data.train, aabb, NeusConfig.preset("cpu"), workdir=out)
    field.sdf(points), field.albedo(points, normals), field.render(K, T_turntable_cam, w, h)
"""

from n2d_reconstruct.neus.field import NeusField
from n2d_reconstruct.neus.trainer import NeusConfig, train_neus

__all__ = ["NeusConfig", "NeusField", "train_neus"]

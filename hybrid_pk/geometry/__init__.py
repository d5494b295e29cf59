"""Geometry on plain tensors: SO(3)/SE(3) maps, frame registration, batch-last algebra.

The lowest layer of the package: it imports nothing else of hybrid_pk but errors.
"""

from hybrid_pk.geometry import rotations
from hybrid_pk.geometry.rotations import axis_near_pi as axis_near_pi
from hybrid_pk.geometry.rotations import matrix_to_quat as matrix_to_quat
from hybrid_pk.geometry.rotations import matrix_to_rpy as matrix_to_rpy
from hybrid_pk.geometry.rotations import nearest_rotation as nearest_rotation
from hybrid_pk.geometry.rotations import quat_to_matrix as quat_to_matrix
from hybrid_pk.geometry.rotations import rotation_angle as rotation_angle
from hybrid_pk.geometry.rotations import rpy_to_matrix as rpy_to_matrix
from hybrid_pk.geometry.rotations import skew as skew
from hybrid_pk.geometry.rotations import so3_exp as so3_exp
from hybrid_pk.geometry.rotations import so3_left_jacobian as so3_left_jacobian
from hybrid_pk.geometry.rotations import so3_log as so3_log
from hybrid_pk.geometry.rotations import transform as transform
from hybrid_pk.geometry.rotations import transform_inverse as transform_inverse
from hybrid_pk.geometry.rotations import twist_swing as twist_swing
from hybrid_pk.geometry.rotations import vee_antisym as vee_antisym
from hybrid_pk.geometry.shapes import broadcast_shapes as broadcast_shapes

__all__ = [*rotations.__all__, "broadcast_shapes"]

"""Files: the model file, hybrid models in it, and the corrected URDF.

The one layer that knows every model type (extended model, hybrid networks):

- :mod:`~hybrid_pk.io.model_file`: :func:`save_model` / :func:`load_model`, one
  self-contained file that ``calibrate`` writes and ``evaluate``, ``train``, ``ik`` read;
- :mod:`~hybrid_pk.io.hybrid_file`: :func:`save_hybrid` / :func:`load_hybrid` and
  prediction with whatever a model file holds;
- :mod:`~hybrid_pk.io.urdf_export`: the geometric part of a calibrated model as a
  corrected URDF;
- :mod:`~hybrid_pk.io.dh_export`, :mod:`~hybrid_pk.io.ur_calibration`: the same as a DH /
  modified-DH table or as Universal Robots' kinematics YAML, and
  :mod:`~hybrid_pk.io.export_summary` what such a file cannot carry.
"""

from hybrid_pk.io import hybrid_file, model_file, urdf_export
from hybrid_pk.io.dh_export import model_dh_table as model_dh_table
from hybrid_pk.io.dh_export import write_dh_yaml as write_dh_yaml
from hybrid_pk.io.export_summary import left_out as left_out
from hybrid_pk.io.hybrid_file import forward_model as forward_model
from hybrid_pk.io.hybrid_file import load_hybrid as load_hybrid
from hybrid_pk.io.hybrid_file import networks_used as networks_used
from hybrid_pk.io.hybrid_file import predict_poses as predict_poses
from hybrid_pk.io.hybrid_file import save_hybrid as save_hybrid
from hybrid_pk.io.model_file import FORMAT_TAG as FORMAT_TAG
from hybrid_pk.io.model_file import FORMAT_VERSION as FORMAT_VERSION
from hybrid_pk.io.model_file import NOMINAL_PREFIX as NOMINAL_PREFIX
from hybrid_pk.io.model_file import LoadedModel as LoadedModel
from hybrid_pk.io.model_file import load_model as load_model
from hybrid_pk.io.model_file import model_robot as model_robot
from hybrid_pk.io.model_file import save_model as save_model
from hybrid_pk.io.ur_calibration import write_ur_calibration as write_ur_calibration
from hybrid_pk.io.urdf_export import BASE_LINK_NAME as BASE_LINK_NAME
from hybrid_pk.io.urdf_export import TOOL_LINK_NAME as TOOL_LINK_NAME
from hybrid_pk.io.urdf_export import corrected_urdf as corrected_urdf
from hybrid_pk.io.urdf_export import export_urdf as export_urdf

__all__ = [
    *model_file.__all__,
    *hybrid_file.__all__,
    *urdf_export.__all__,
    "left_out",
    "model_dh_table",
    "write_dh_yaml",
    "write_ur_calibration",
]

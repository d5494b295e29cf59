"""Files: the model file, hybrid models in it, and the corrected URDF.

The one layer that knows every model type (extended model, hybrid networks):

- :mod:`~hybrid_pk.io.model_file`: :func:`save_model` / :func:`load_model`, one
  self-contained file that ``calibrate`` writes and ``evaluate``, ``train``, ``ik`` read;
- :mod:`~hybrid_pk.io.hybrid_file`: :func:`save_hybrid` / :func:`load_hybrid` and
  prediction with whatever a model file holds;
- :mod:`~hybrid_pk.io.urdf_export`: the geometric part of a calibrated model as a
  corrected URDF.
"""

from hybrid_pk.io import hybrid_file, model_file, urdf_export
from hybrid_pk.io.hybrid_file import forward_model as forward_model
from hybrid_pk.io.hybrid_file import load_hybrid as load_hybrid
from hybrid_pk.io.hybrid_file import predict_poses as predict_poses
from hybrid_pk.io.hybrid_file import save_hybrid as save_hybrid
from hybrid_pk.io.model_file import FORMAT_TAG as FORMAT_TAG
from hybrid_pk.io.model_file import FORMAT_VERSION as FORMAT_VERSION
from hybrid_pk.io.model_file import NOMINAL_PREFIX as NOMINAL_PREFIX
from hybrid_pk.io.model_file import LoadedModel as LoadedModel
from hybrid_pk.io.model_file import load_model as load_model
from hybrid_pk.io.model_file import model_robot as model_robot
from hybrid_pk.io.model_file import save_model as save_model
from hybrid_pk.io.urdf_export import BASE_LINK_NAME as BASE_LINK_NAME
from hybrid_pk.io.urdf_export import TOOL_LINK_NAME as TOOL_LINK_NAME
from hybrid_pk.io.urdf_export import corrected_urdf as corrected_urdf
from hybrid_pk.io.urdf_export import export_urdf as export_urdf

__all__ = [*model_file.__all__, *hybrid_file.__all__, *urdf_export.__all__]

"""Camera parameterisations: how the unknowns of one camera map to its projections.

* :mod:`~planetref.adjust.models.protocol` - :class:`AdjustableCamera`, the protocol the
  solver sees, with :class:`Evaluation` and :class:`CoverageIssue`.
* :mod:`~planetref.adjust.models.linescan` - :class:`LineScanParameterization`, the
  native line-scan strip (node EOPs, interior orientation, CCD placement) on the
  camera's own projection kernel.
* :mod:`~planetref.adjust.models.csm` - :class:`CsmParameterization`, usgscsm's
  per-image corrections of a CSM line-scan camera (central finite differences).
* :mod:`~planetref.adjust.models.factory` - :func:`parameterize`, which picks one.
"""

from planetref.adjust.models.csm import CsmParameterization
from planetref.adjust.models.factory import parameterize
from planetref.adjust.models.linescan import LineScanParameterization
from planetref.adjust.models.protocol import AdjustableCamera, CoverageIssue, Evaluation

__all__ = [
    "AdjustableCamera",
    "CoverageIssue",
    "CsmParameterization",
    "Evaluation",
    "LineScanParameterization",
    "parameterize",
]

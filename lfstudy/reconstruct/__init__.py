"""Volume reconstruction (thesis sec. 5.5–5.6): a registry of methods found by name.

Modules: :mod:`~lfstudy.reconstruct.registry` (``reconstruct``,
``register_method``) and :mod:`~lfstudy.reconstruct.threshold` (sec. 5.5
threshold + dilation, and ``"none"``: the focal stack as is). Importing this
package registers every built-in method.
"""

from __future__ import annotations

from lfstudy.reconstruct.registry import available_methods, reconstruct, register_method
from lfstudy.reconstruct.threshold import disk, focal_stack_as_is, threshold_dilate

__all__ = ["reconstruct", "register_method", "available_methods", "threshold_dilate", "focal_stack_as_is", "disk"]

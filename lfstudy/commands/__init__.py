"""Sub-commands of the ``lfstudy`` CLI, one module each (see :mod:`lfstudy.cli`)."""

"""Sub-commands of the ``psmini`` command, one module each (see :mod:`psmini.cli`)."""

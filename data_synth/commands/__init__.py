"""psmini sub-commands that need the test bed (``demo``, ``synth``), plugged into ``psmini`` by entry points."""

"""Tests of psmini.rig: firmware, protocol, controller, camera, sessions and the simulated rig."""

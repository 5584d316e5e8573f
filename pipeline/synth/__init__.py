"""Synthetic scenes: rendering people seen by a calibrated rig."""

"""Headless rendering shared by synth and evaluation: the pyrender/EGL loader and depth renders."""

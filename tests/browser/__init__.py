"""A package: the browser test modules import what conftest.py shares."""

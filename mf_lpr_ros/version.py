"""The package version, in a module of its own so that nothing imports the package's __init__
to read it (setup.py and package.xml carry the same number; test_architecture checks them)."""

__version__ = "0.1.0"

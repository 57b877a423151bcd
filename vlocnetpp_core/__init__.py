"""VLocNet++ core: network, data, training, evaluation and streaming inference. No ROS imports here."""

__version__ = "0.1.0"


def lazy_getattr(package: str, exports: dict[str, str], namespace: dict):
    """A package's module ``__getattr__`` (PEP 562): ``name`` imports ``package.<exports[name]>`` on first use and is
    kept in ``namespace`` (the package's ``globals()``), so importing the package imports none of its modules."""
    import importlib

    def __getattr__(name: str):
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = namespace[name] = getattr(importlib.import_module(f"{package}.{module}"), name)
        return value

    return __getattr__

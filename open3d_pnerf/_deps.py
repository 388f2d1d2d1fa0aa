"""Import-time check of the two dependencies that come as CPU and CUDA builds."""

_HINT = (
    "{name} is not installed. On a CPU machine: `pip install torch==2.13.0` then "
    "`pip install 'open3d_pnerf[cpu]'`. With a GPU: install CUDA builds of torch (PyTorch "
    "index) and open3d (`pip install open3d==0.19.0`, needs the system library "
    "libusb-1.0-0), then `pip install open3d_pnerf`."
)


def require(name: str):
    """Import and return module `name`, or raise ImportError with install instructions."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError as exc:  # pragma: no cover - depends on the environment
        msg = _HINT.format(name=name)
        if "libusb" in str(exc):
            msg = (
                f"open3d failed to import: {exc}. The full open3d wheel needs libusb-1.0 "
                "(`apt-get install libusb-1.0-0`); or use `pip install open3d-cpu==0.19.0`."
            )
        raise ImportError(msg) from exc

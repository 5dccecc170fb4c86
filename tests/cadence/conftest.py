import os

os.environ.setdefault("XDG_RUNTIME_DIR", "/tmp/xdg")
os.makedirs(os.environ["XDG_RUNTIME_DIR"], exist_ok=True)


def assert_unlinked(*names: str) -> None:
    """The named segments are gone (checked by name: other suites create segments concurrently)."""
    left = [n for n in names if os.path.exists(os.path.join("/dev/shm", n))]
    assert not left, f"leaked shared-memory segments: {left}"

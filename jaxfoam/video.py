"""Video files through imageio-ffmpeg without JAX's fork warning."""
from __future__ import annotations

import contextlib
import warnings


@contextlib.contextmanager
def ffmpeg_subprocess():
    """Silence JAX's os.fork warning while imageio-ffmpeg runs ffmpeg as a subprocess.

    imageio-ffmpeg starts ffmpeg through `subprocess` (fork and exec at once), and JAX's at-fork hook
    warns that a forked child of a multithreaded process may deadlock. The child execs ffmpeg at once
    and runs no Python or JAX code, so that warning does not apply; any other warning still shows.
    """
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r"os\.fork\(\) was called", category=RuntimeWarning)
        yield

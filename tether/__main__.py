"""`python -m tether` and the `tether` script: the whole CLI, except that `run SERVICE` loads only that service.

A systemd unit or a container runs `tether run SERVICE`; through `main` it loads tether.runservice
and that service's package, never tether.cli (whose other commands pull in mcap, rich, pinocchio ...).
"""

import sys
import threading


def main() -> None:
    """The `tether` script's entry point (pyproject.toml [project.scripts]); exits with the command's code.

    A command that ends while another thread still runs ends without Python's finalization
    (tether.runservice.leave), with the same exit code and output. Such a thread may be at work in
    Zenoh: `tether send` leaves the fetch of its goal's result waiting, a Ctrl-C the call it
    interrupted, and zenoh runs each Python callback (a subscriber's, a matching listener's) on a
    thread of its own until a moment after its undeclaration. Woken as the interpreter finalizes, that
    thread is made to exit inside zenoh's Rust frames and the process dies (SIGABRT, or SIGSEGV): a
    crash's exit status, and the JSON it printed lost when that came before stdout's flush. What
    `leave` skips: waiting for threads that are not daemons (the CLI's own are joined by their command,
    or, after a Ctrl-C, only read), exit handlers (logging's, which `leave` runs; multiprocessing's,
    which no command gives a process to stop; foxglove's, whose `tether view` ends so already) and the
    last garbage collection (each command has closed its sessions, files and temporary directories).
    """
    from tether.runservice import exit_status, leave, runs_a_service

    if runs_a_service(sys.argv[1:]):
        from tether.runservice import app
    else:
        from tether.cli import app
    try:
        app()
    except SystemExit as ended:
        if threading.active_count() > 1:
            leave(exit_status(ended))
        raise
    except Exception:
        if threading.active_count() > 1:
            sys.excepthook(*sys.exc_info())  # the traceback, as the interpreter would print it
            leave(1)
        raise


if __name__ == "__main__":
    main()

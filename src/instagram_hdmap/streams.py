"""The job's standard streams when they misbehave: a reader that goes away (``| head -1``), a stream closed at the
start (``2>&-``) or on a full disk, a terminal of another encoding. ``cli.main`` wraps stdout and stderr in a
``ReportStream`` for the whole job."""

from __future__ import annotations

import contextlib
import errno
import io
import os
import select
import sys


def stdout_gone() -> bool:
    """Whether stdout's reader has gone (its pipe is closed), not another pipe's (a data-loader worker's): the
    write end of a pipe without a reader polls as an error."""
    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(events & (select.POLLERR | select.POLLHUP) for _, events in poller.poll(0))
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):  # no file descriptor (tests, notebooks)
        return True


def to_devnull(stream) -> None:
    """Point ``stream``'s descriptor at /dev/null, so that the interpreter's last flush (and a child process) does not
    fail on the closed pipe again; nothing where the stream has no descriptor (tests, notebooks)."""
    with contextlib.suppress(OSError, ValueError, AttributeError, io.UnsupportedOperation):
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, stream.fileno())
        os.close(devnull)


class ReportStream:
    """stdout or stderr of a job whose reader may go away (``evaluate-json ... --out m.json | head -1``, ``train ...
    2>&1 | head``, a ``tee`` that was killed): the job goes on and writes its files, the messages nobody reads are
    dropped (the descriptor then points at /dev/null, for the interpreter's last flush and for child processes), and
    ``main`` returns 141 at the end, as SIGPIPE's exit status. Without it the first message after the reader left
    stopped the job: evaluate-json's metrics file unwritten, a training stopped before its first step. Likewise a
    stream closed at the start (EBADF) and stderr on a full disk (its messages dropped, a note on stdout at the end);
    a line that the stream's encoding cannot hold is escaped; stdout's other errors (a full disk: the results are
    lost) are raised, naming the stream."""

    def __init__(self, stream, name: str):
        self._stream = stream
        self.name = name  # named in an error of the stream: a full disk under `> log` said no file
        self.gone = False  # its reader went away during the job
        self.closed = False  # closed before the job (`2>&-`): messages dropped, the exit status kept
        self.lost: OSError | None = None  # stderr's write that failed (a full disk under `2> log`): the rest dropped

    def _reader_left(self) -> None:
        self.gone = True
        to_devnull(self._stream)

    def write(self, text):
        if not (self.gone or self.closed):
            try:
                try:
                    return self._stream.write(text)
                except UnicodeEncodeError:  # a path with an 'ä' on an ASCII / Latin-1 terminal (PYTHONIOENCODING,
                    encoding = self._stream.encoding  # a Windows console): was a traceback, exit 1, after the work
                    return self._stream.write(text.encode(encoding, "backslashreplace").decode(encoding))
            except OSError as e:
                self._failed(e)
        return len(text)

    def flush(self) -> None:
        if not (self.gone or self.closed):
            try:
                self._stream.flush()
            except OSError as e:
                self._failed(e)

    def _failed(self, e: OSError) -> None:
        if isinstance(e, BrokenPipeError):
            self._reader_left()
        elif e.errno == errno.EBADF:  # closed at the start, another file on its descriptor (a launcher's script)
            self.closed = True
        elif self.name == "the standard error":  # messages only (progress bars, notes): a full disk under `2> log`
            self.closed, self.lost = True, e  # stopped a training at its next bar, exit 1, unsaved and unsaid
        else:
            raise self._named(e) from e

    def _named(self, e: OSError) -> OSError:
        return e if e.filename is not None or e.errno is None else OSError(e.errno, e.strerror, self.name)

    def __getattr__(self, name):
        return getattr(self._stream, name)

"""A server's own error, carried through an FTM to the client as the server worded it.

rospy writes a handler's error as ``service cannot process request: <text>`` (the handler raised
ServiceException) or ``error processing request: <text>`` (any other exception), and the caller
reads it back as ``service [<name>] responded with an error: b'<written>'``. Proceed calls the
replica's server (``/master/account``); the client called the Proxy (``/account``). So Proceed
keeps only what the server wrote (:func:`as_written`), and the Proxy writes it again the same way
(:func:`to_raise`): the client reads what calling the server directly would have given it, with no
replica's name in it.
"""
import ast
import re

_READ = re.compile(r'^service \[[^\]]*\] responded with an error: (.*)$', re.S)
SERVICE_EXCEPTION = 'service cannot process request: '
OTHER_EXCEPTION = 'error processing request: '


def as_written(message):
    """What the server wrote, from the message of the ServiceException a ServiceProxy raised."""
    match = _READ.match(message)
    if not match:
        return message
    written = match.group(1)
    if written[:2] in ("b'", 'b"'):
        try:
            written = ast.literal_eval(written).decode('utf-8', 'replace')
        except (ValueError, SyntaxError):
            pass
    return written


def to_raise(written):
    """(exception kind, its message) that makes rospy write ``written`` back: 'service' for a
    ServiceException, 'other' for another exception. Text the server did not write (a mechanism's
    own error) is raised as a ServiceException."""
    if written.startswith(SERVICE_EXCEPTION):
        return 'service', written[len(SERVICE_EXCEPTION):]
    if written.startswith(OTHER_EXCEPTION):
        return 'other', written[len(OTHER_EXCEPTION):]
    return 'service', written

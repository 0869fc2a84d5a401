"""A service's state on stable storage, restored only after a sanity check (third paper, 3.4).

:meth:`StateStore.save` writes the state as JSON with a SHA-256 checksum, atomically (a temporary
file renamed over the old one: a crash while saving leaves the previous state whole).
:meth:`StateStore.load` restores it only if the checksum matches and the service's own range check
accepts it; otherwise it falls back to a clean start and says why. The service manager tells a
service where its file is (AFT_STATE_FILE) and whether to restore it (AFT_RESTORE_STATE).
"""
import hashlib
import json
import os
import tempfile


def _digest(payload):
    return hashlib.sha256(payload.encode()).hexdigest()



NO_STATE = 'no saved state'   # load()'s reason when nothing was ever saved (a fresh start)

class StateStore(object):
    """``check(state)`` returns None when the state is sane, else what is wrong with it (the range
    check of the service, e.g. a joint position outside its limits)."""

    def __init__(self, path, check=None):
        self.path = path
        self.check = check or (lambda state: None)

    def save(self, state):
        payload = json.dumps(state, sort_keys=True)
        record = json.dumps({'sha256': _digest(payload), 'state': payload})
        folder = os.path.dirname(os.path.abspath(self.path))
        os.makedirs(folder, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=folder, prefix='.state-')
        try:
            with os.fdopen(fd, 'w') as f:
                f.write(record)
                f.flush()
                os.fsync(f.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            if os.path.exists(tmp):
                os.unlink(tmp)
            raise
        # The rename itself made durable: without it a power loss just after could bring the old file
        # back (a witness would then grant an epoch again).
        directory = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)

    def load(self):
        """(state, None) when the saved state passes every check; (None, why) for a clean start."""
        try:
            with open(self.path) as f:
                text = f.read()
        except FileNotFoundError:
            return None, NO_STATE
        except OSError as e:
            return None, 'saved state unreadable: %s' % e.strerror
        try:
            record = json.loads(text)
            payload, digest = record['state'], record['sha256']
        except (ValueError, TypeError, KeyError):
            return None, 'saved state corrupt: not a state record'
        if not isinstance(payload, str) or _digest(payload) != digest:
            return None, 'saved state corrupt: checksum mismatch'
        state = json.loads(payload)
        problem = self.check(state)
        if problem:
            return None, 'saved state out of range: %s' % problem
        return state, None

    def clear(self):
        try:
            os.unlink(self.path)
        except FileNotFoundError:
            pass


def from_environment(default_path, check=None, environ=None):
    """The store and whether to restore it, as the service manager set them for this service:
    (StateStore, restore) from AFT_STATE_FILE and AFT_RESTORE_STATE (default: default_path, no)."""
    environ = os.environ if environ is None else environ
    path = environ.get('AFT_STATE_FILE') or default_path
    return StateStore(path, check), environ.get('AFT_RESTORE_STATE', '0') == '1'

"""What a replica's Recovery node does when its crash detector declares the peer failed."""
import enum

from .protocol import Role


class Step(enum.Enum):
    FAIL_SILENCE = 'kill whatever is left of the failed site'
    PROMOTE_AFTER = "fence the After against the old primary's checkpoints and make it ALONE"
    PROMOTE_PROTOCOL = "make the Protocol ALONE once it stored every checkpointed reply"
    BIND_CLIENT = "bind the Protocol to the clients' request and reply topics"
    AFTER_ALONE = 'stop checkpointing: release the replies held for the lost backup'


def plan(role):
    """The steps, in order, when the peer of a replica in ``role`` has failed."""
    if role == Role.BACKUP:
        return [Step.FAIL_SILENCE, Step.PROMOTE_AFTER, Step.PROMOTE_PROTOCOL, Step.BIND_CLIENT]
    if role == Role.PRIMARY:
        return [Step.FAIL_SILENCE, Step.AFTER_ALONE]
    return []   # ALONE: nobody left to lose


# Steps that may run while FAIL_SILENCE is still killing the failed site: none of them lets this
# replica answer a client. Every other step waits until fail-silence is complete.
OVERLAP_FAIL_SILENCE = frozenset([Step.PROMOTE_AFTER, Step.PROMOTE_PROTOCOL, Step.AFTER_ALONE])


def role_after(role):
    """The replica's role once the plan for its peer's failure is carried out."""
    return Role.ALONE if role in (Role.BACKUP, Role.PRIMARY) else role


def same_process(create_time, last_heard_wall, tolerance=0.05):
    """True if a process created at create_time could have sent a heartbeat at last_heard_wall.

    Guards fail-silence against a pid reused by an unrelated process after the site died.
    """
    return create_time <= last_heard_wall + tolerance

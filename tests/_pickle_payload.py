"""A pickled object that records it was executed: loading it must never run it (``weights_only=True`` refuses it)."""

EXECUTED = []


def _mark_executed():
    EXECUTED.append(True)
    return {}


class Payload:
    def __reduce__(self):
        return (_mark_executed, ())

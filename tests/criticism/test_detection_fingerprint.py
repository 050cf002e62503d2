"""The detection study's library fingerprint ignores what computes nothing (docstrings, comments,
layout) and moves with any change to the code."""

from benchmarks.bench_detection import code_without_docstrings

SOURCE = '''"""Module docstring."""


def gap(x, y):
    """The gap."""
    return y - x  # bumper to bumper
'''

REWORDED = '''"""Another module docstring, reflowed
over two lines."""
def gap(x,
        y):
    """A reworded docstring."""
    # a comment of its own line
    return y - x
'''

CHANGED = SOURCE.replace("y - x", "x - y")


def test_docstrings_comments_and_layout_do_not_move_the_fingerprint_and_code_does():
    assert code_without_docstrings(REWORDED) == code_without_docstrings(SOURCE)
    # Negative control: the same layout with the code changed.
    assert code_without_docstrings(CHANGED) != code_without_docstrings(SOURCE)
    # A function that holds only a docstring keeps a body.
    assert (
        code_without_docstrings('def f():\n    """Only a docstring."""\n') == "def f():\n    pass"
    )

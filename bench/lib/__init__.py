"""What the benchmarks share: ``data`` (the data sets, their banks, the errors of a pose against a gt
line), ``policy`` (command-line options that build a ``Policy`` to pass to the estimate), ``teach`` (parts
taught from a set's own images), ``fit`` (the verification score's fit) and ``scenes`` (the test part of
the rendered-scene benchmarks).

The benchmarks change the estimate only through the ``Policy`` they pass it: nothing in bench/ writes a
service module's globals. Tests of the bench tools themselves are in ``bench/tests``::

    python -m pytest bench/tests -q
"""

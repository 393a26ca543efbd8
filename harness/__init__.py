"""The test harness around the product: what runs the simulated robot through the product.

``bsc demo`` (the paper's capture scenario end to end, judged against the simulator's truth),
``bsc sim`` and the degradation series of ``bsc sim --series``. It depends on the product
(``gateway``, ``drivers``) and on the simulator; the product depends on neither (an import-linter
contract in the test suite says so), so a deployment beside a real robot needs no simulator.
"""

"""Evidence for jaxfoam: validation against known solutions, stability maps, accuracy against speed.

Run `python -m experiments all --quick` (reduced, minutes) or `python -m experiments NAME [--quick]`.
"""

"""The base of jaxfoam's own errors: `except jaxfoam.JaxfoamError` catches every one of them."""


class JaxfoamError(Exception):
    """Base class of the errors jaxfoam raises for bad input or a failed run (each also subclasses
    the built-in error it refines, e.g. ValueError or FloatingPointError)."""

"""Warnings and errors specific to lrmfrf."""

__all__ = ["IdentifiabilityWarning"]


class IdentifiabilityWarning(UserWarning):
    """Some frequency bins could not be identified from the data.

    Raised (as a warning) when the input does not excite every aliased band in
    some local windows, so their local problems are rank-deficient. Those bins
    are marked ``valid_ = False`` and hold NaN.
    """

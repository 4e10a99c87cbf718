"""PIPE: Process Informed Parameter Estimation.

Learns how the contact model of a robot assembly task depends on the part's geometry, so that the
contact model and the insertion force of a new part are predicted from its CAD mesh alone.
"""

__version__ = "0.3.0"

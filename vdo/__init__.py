"""vdo: virtual design of multi-camera DIC experiments."""

import logging

from .configure import configure

logging.getLogger(__name__).addHandler(logging.NullHandler())

"""Rational polynomial coefficients (RPCs) and a camera on them."""

from planetref.camera.rpc.model import *  # noqa: F403

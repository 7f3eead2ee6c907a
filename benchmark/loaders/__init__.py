"""Motion-data loaders: AMASS ``.npz``, BVH (CMU defaults), and conversion to the harness ``.npz``.
"""

from benchmark.loaders.amass import load_amass
from benchmark.loaders.bvh import load_bvh
from benchmark.loaders.bvh_format import parse_bvh, write_bvh
from benchmark.loaders.convert import convert, load_motion

__all__ = ["load_amass", "load_bvh", "parse_bvh", "write_bvh", "convert", "load_motion"]

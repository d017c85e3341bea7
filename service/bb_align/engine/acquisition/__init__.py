"""Multi-hypothesis acquisition: stage 1 for pairs up to 100 m apart (not in the paper; docs/acquisition.md).

At long range the nearest-neighbour descriptor match is right for only a few peer keypoints, but the true partner
is usually among the few nearest. So, instead of the paper's one RANSAC fit on nearest neighbours
(``Acquirer.__call__``, Algorithm 1 lines 9-11 in multi mode):

1. candidates (``candidates``): the ``top_k`` nearest ego keypoints (by descriptor, over all orientation offsets and
   180-degree copies) of every peer keypoint;
2. hypotheses (``hypotheses``, loops in ``kernels``): every pair of candidates whose lengths agree votes for the
   rigid pose it implies; the strongest distinct peaks are refitted (Kabsch); the boxes both cars detected and a
   prior propose more;
3. verification (``verification``): each hypothesis is refined coarsely and scored by its dense overlap; the
   ``finalists`` best are refined fully and scored again;
4. decision (``decision``, ``free_space``): the best must beat the runner-up (a distinct pose) by ``min_margin`` and
   explain enough of what the two images can share, or the boxes must single it out; no rival beyond stage 2's
   reach may have the boxes' vote; the free space rules out aliases. ``engine.verdict`` judges these facts.

Everything is config-driven (``AcquireConfig``) and reuses the ego frame's cached features.
"""

from .acquirer import Acquirer
from .model import Acquisition, Hypothesis, PriorWindow, SearchMemo

__all__ = ["Acquirer", "Acquisition", "Hypothesis", "PriorWindow", "SearchMemo"]

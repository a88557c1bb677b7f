"""Localize a learned object in a scene image: 2D alignment, 6D pose, refinement.

DESIGN.md §2 steps 6-8: features of the scene (on a pyramid level small enough
to stay fast), probabilistic alignment of the model views, at each matched
location a search over all training views for the one that explains the image
edges best (:mod:`viewloc_core.view_search`; locations are ranked by its
evidence), the 6D pose from the similarity (paper §4.2) and, when the model
has a contour model, the refinement against image edges (§5.2's scene-based
tracking).
"""

from __future__ import annotations

import math
import threading
import time
import weakref
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import cv2
import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from viewloc_core import (
    colour_kernels,
    contour_kernels,
    feature_kernels,
    gauss_newton_kernel,
    near_pairs,
    normal_search,
    pairing,
    part_colour,
    refine_kernels,
    sample_evidence,
    seeding,
    shading_kernels,
    shift_search,
    similarity_fit,
)
from viewloc_core import similarity as sim2
from viewloc_core.align import (
    AlignConfig,
    Match2D,
    ModelIndex,
    align,
    build_index,
    coverage,
    log_probability,
    refine_at_model_scale,
)
from viewloc_core.both_cores import each_on_both
from viewloc_core.camera import Camera
from viewloc_core.colour_edges import with_colour_boundary
from viewloc_core.contour_model import ContourModel
from viewloc_core.detection import Detection, Similarity2D
from viewloc_core.distinct_parts import distinct_parts
from viewloc_core.edge_contrast import local_min_gradient
from viewloc_core.edge_evidence import ChanceRates, chance_rates
from viewloc_core.errors import InvalidInputError
from viewloc_core.features import (
    ImageFeatures,
    extract_features,
    orientation_bin,
    to_grey_float,
)
from viewloc_core.figure_ground import MIN_PIXELS as MIN_RING_PIXELS
from viewloc_core.figure_ground import figure_ground_contrast, ring_values
from viewloc_core.hidden_fits import lies_hidden_behind
from viewloc_core.interior_edges import interior_edges
from viewloc_core.model import ObjectModel, cached_per_model
from viewloc_core.near_symmetry import NearSymmetries, near_symmetries
from viewloc_core.pose import Pose
from viewloc_core.pose_determinacy import rotation_std_deg
from viewloc_core.pose_from_match import pose_from_similarity
from viewloc_core.refine import (
    EdgePyramid,
    RefinementResult,
    RefineOptions,
    contour_in_image_fraction,
    prepare_edges,
    project_contour_view,
    refine_pose,
)
from viewloc_core.search_space import DepthRange, ImageRegion
from viewloc_core.shading import (
    SurfaceSamples,
    shading_agreement,
    surface_samples,
    visible_samples,
)
from viewloc_core.symmetry import (
    Symmetries,
    any_within_angle_deg,
    canonical_pose,
    within_angle_deg,
)
from viewloc_core.view_search import (
    FIT_RADII_PX,
    OTHER_SIDE_MIN_DEG,
    ViewCandidate,
    ViewTemplates,
    best_member,
    search_views,
    view_templates,
)

#: Search-level pixels by which the alignment and the colour proposals
#: reach beyond a request's region (``LocalizeOptions.roi``): a
#: hypothesis's position is a few pixels off the part's centre until it is
#: fitted.
REGION_SLACK_PX = 4.0

#: Images larger than this (longest side, px) are searched on a pyramid level.
#: Fine texture (cloth, cast surfaces, printed backgrounds) makes dense edges
#: that swamp the part's outline; at a coarser level they blur away while the
#: outline stays. Measured on the hard bench set (640x480, textured): 38 of 80
#: found at 700 px, 32 at 480, 38 at 400 and at 320; 400 keeps a part of 120 px
#: in a 1280x1024 image at about 40 px, the least the features need.
#: Measured again in session 78 (make bench, learning seed 0), 640 (the full
#: image) against 400: hard rec2D 0.9625 -> 0.9125, AR_MSSD 0.909 -> 0.839;
#: novel 0.942 -> 0.942, 0.885 -> 0.853; LM-O no gain (session 77); but the
#: shop set's thin parts (a shaft and a bolt shank 14-22 mm across, 7-12 px
#: at the search level at 700 mm) gain: rec2D 0.75 -> 0.82, AR_MSSD 0.652 ->
#: 0.709. So a search that settles nothing on this level is repeated on a
#: finer one (:data:`FINER_SEARCH_SIDE_PX`, :func:`localize_in_scene`).
MAX_SEARCH_SIDE_PX = 400

#: The longest side (px) of the level searched again when the first search
#: settles nothing (:func:`localize_in_scene`): the full image up to
#: 640x480, the size the bench measured it on, and a level of that size for
#: larger images, whose search at full resolution would cost more while
#: the part's thin features are resolved already.
FINER_SEARCH_SIDE_PX = 640

#: A first search whose best fit confirms at least this share of its
#: contour, beyond chance as well, is not repeated on the finer level even
#: when the fit has not settled (its figure-ground contrast is low: a metal
#: part on a grey floor, a part coloured like its background): the outline
#: was resolved on this level, and what settling guards against, a fit to
#: a cast shadow or a texture, the spares of this level have answered
#: already. Learning seed 0, first searches that did not settle and ran
#: the finer one: hard set 38, novel 59, shop 53; of those, 8, 13 and 14
#: had their best fit confirmed at 0.9 both ways, and the finer search
#: made none of them right that was not (it did in 1, 3 and 5 of the
#: others, all confirmed less: at most 0.89 beyond chance). Searched once
#: after such fits: the same detections on those sets at learning seeds 0
#: and 1 but one shop plate at seed 1, which the finer search had turned
#: wrong; mean latency 7-10 % lower (paired runs in one process: hard 98
#: -> 89 ms, novel 123 -> 113, shop 157 -> 145).
FINER_SEARCH_NEEDLESS_FRACTION = 0.9

#: The final refinement; its chance rate ranks fits that are not confirmed.
#: It ends with a polishing stage that searches 4 px along the normals
#: (RefineOptions.polish_px). Hard bench set, learning seeds 0-4: AR_MSSD
#: 0.84/0.855/0.735/0.766/0.7975 -> 0.854/0.8775/0.746/0.816/0.816 (mean
#: 0.799 -> 0.822), AR_MSPD mean 0.837 -> 0.8475; polishing 3 px 0.817,
#: 5 px 0.818, 4 px for 3 or 10 steps 0.814 / 0.821, every quick fit
#: polished too 0.815, and a finest-level search of 4 px from the start
#: 0.812 (the free-form part, fitted from rough starts, lost two poses).
#: Paper set 0.989/0.993 -> 0.994/0.993. LM-O ape, can, cat: 0.142/0.205
#: -> 0.143/0.205 (ape 0.113 -> 0.105, can 0.111 -> 0.116, cat 0.208 ->
#: 0.214); images without the part given a detection: hard 51 -> 52 of
#: 60, paper 3 -> 4 of 10, LM-O 5 -> 7 of 18.
FINAL_REFINE = RefineOptions(polish_px=4)

#: Short fit that compares extra starts: 3 iterations on the coarse level,
#: then 3 on the full-resolution one, on every second contour point. Its
#: inlier fraction is measured at full resolution, where the fits it
#: competes with ended: one that stopped on the coarse level confirms less
#: of its contour there than its full fit would, wherever it started.
#: Hard bench set, models learned with seeds 0-4, coarse level only ->
#: both: AR_MSSD 0.84/0.775/0.706/0.764/0.739 -> 0.84/0.795/0.724/0.769/0.764,
#: AR_MSPD mean 0.802 -> 0.816; images without the part given a detection
#: 46 -> 49 of 60. LM-O ape, can and cat: seed 0 0.144/0.204 -> 0.142/0.206,
#: seed 1 0.146/0.209 -> 0.151/0.208. About 1-2 ms per image.
QUICK_REFINE = RefineOptions(iterations=(3, 3), measure_chance=False,
                             measure_uncertainty=False, point_stride=2)

#: The short fit of a near-symmetric twin of a fit (see ``_other_sides``):
#: the twin turns about the part's centroid, whose image stays where the
#: fit put it, so the search for a 2D shift is skipped.
TWIN_REFINE = replace(QUICK_REFINE, shift_search_px=0.0)

#: The refinements' pyramid (RefineOptions.levels, search_px, iterations,
#: shift_search_px) is set for images up to about this long side (px). A
#: larger image of the same scene shows the part larger, and the start the
#: search level gives is off by as many more full-resolution pixels: each
#: doubling of the long side beyond it adds a coarser level to start on
#: (:func:`_refine_levels`), where the start's error and the part look as
#: they would in an image of this size.
REFINE_REFERENCE_SIDE_PX = 640

#: A refinement that confirms this share of the contour needs no other start
#: (true poses: median 0.90, 10th percentile 0.79 on the paper set; fits
#: stuck at a wrong depth 0.6-0.75).
GOOD_FIT_FRACTION = 0.85

#: Spare image locations are searched only with at least this share of the
#: best location's alignment evidence (see ``localize``); they are fitted
#: only with SPARE_MIN_VIEW_EVIDENCE_SHARE of the best view-search evidence.
#: The alignment's evidence is the rougher: hard bench set, a part whose
#: location had 0.45 of the best alignment evidence had 0.85 of the best
#: view-search evidence and the best fit (0.5 -> 0.4 with three spares,
#: learning seeds 0-4: one more right detection; paper set and LM-O ape,
#: can, cat unchanged).
SPARE_EVIDENCE_SHARE = 0.4

#: The alignment proposes at least this many locations (more when more
#: detections are wanted: ALIGNED_LOCATIONS_PER_DETECTION) for the view search,
#: whose evidence, not the alignment's, ranks them. The alignment's order is
#: the rougher one. Hard bench set, learning seeds 0/1/2 (with the outline
#: turns), at least 3 / 4 / 5: AR_MSSD 0.84/0.769/0.669, 0.84/0.775/0.706,
#: 0.8275/0.775/0.706; each location costs about 1.5 ms (view search and
#: alignment extension). Later, with the view search's evidence ranking the
#: fits, 4 -> 5, AR_MSSD at learning seeds 0-4: novel set 0.8333 / 0.8492 /
#: 0.84 / 0.8075 / 0.7958 -> 0.8408 / 0.8492 / 0.8483 / 0.8158 / 0.8033 (a
#: part on a checkerboard, whose phantoms take the first four places:
#: novel checker images were 16 of 23 recognised); hard and paper sets
#: unchanged, LM-O (every second photo) the same AR with one ape photo
#: fewer in 2D; 6: novel 0.8295. On LM-O the fifth view search costs about
#: 10 ms (212 -> 225-232 ms median), on the novel set 1-2 ms.
MIN_ALIGNED_LOCATIONS = 5

#: Locations the alignment proposes per detection wanted (plus one, at least
#: MIN_ALIGNED_LOCATIONS): copies of a part in one image are seen from
#: different sides, and the view search's evidence for one of them was
#: 0.37-0.58 of the best copy's (multi bench set, learning seed 0), so a
#: copy can rank behind several wrong places, or not be proposed at all: of
#: 15 copies missed there, 10 lay beyond the first 2 x 3 + 1 locations.
#: With 4 per detection and further detections held to the spares' bar
#: (:func:`_after_the_first_convincing`), the multi bench set, three
#: copies an image (96), found in 2D / detections elsewhere / AR_MSSD:
#: learning seed 0 78 / 14 / 0.753 -> 82 / 12 / 0.784; learning seed 1
#: 79 / 16 / 0.784 -> 78 / 13 / 0.784; learning seed 2 82 / 13 / 0.794 ->
#: 81 / 11 / 0.794; scenes drawn with seed 1 86 / 8 / 0.8625 -> 86 / 7 /
#: 0.8625. The view search's median 11 -> 15 ms an image, the total 120 /
#: 130 -> 135 / 131 ms (alternating runs, seed 0). Three asked for where
#: one part lies (hard bench set, seed 0): 191 -> 174 detections (78 right
#: first both), median 158 -> 177-186 ms (the fill loop fits further places
#: for the dropped ones). One detection wanted is unchanged: 4 + 1 is
#: MIN_ALIGNED_LOCATIONS.
ALIGNED_LOCATIONS_PER_DETECTION = 4

#: A spare location's fit (see ``localize``) competes with the first ones only
#: when its refinement confirms at least this share of the contour beyond
#: chance (``RefinementResult.score``). Object-free images otherwise get
#: more chances at a false positive: paper bench set, 10 object-free
#: images, two spares competing without it 6 with a detection, with 0.6
#: 3, first fits alone 2. Right spares confirm less in clutter than the
#: first fits (hard set: 0.56-0.6 in some); over the hard set's five
#: learning seeds 0.7 kept 2 fewer right detections than 0.6 (of 400,
#: replayed on recorded fits).
SPARE_MIN_CHANCE_CORRECTED = 0.6

#: A confirmed first fit still gets a spare beside it when its figure-ground
#: contrast (:mod:`viewloc_core.figure_ground`) is under this: its outline
#: may be a cast shadow's or a texture's (hard bench set, wrong locations'
#: median 0.01-0.02, true ones' 0.23-0.30). The ranking then weighs the
#: contrast (FIGURE_GROUND_WEIGHT).
FIRST_FIT_MIN_FIGURE_GROUND = 0.05

#: Locations fitted beside the first ones when one of those is not settled
#: (see ``localize``). With every located place fitted (hard bench set,
#: learning seeds 0-4, 400 images), a fit near the part was among them in
#: 374 images; the first fit and one spare found it in 348, and the next
#: two or three locations hold most of the rest (replayed on those fits,
#: two spares 359, three 364; measured, AR_MSSD mean 0.822 with two, 0.827
#: with three, 0.8305 with three and the settling rule and alignment gate
#: as now, for about 3-4 ms of median time per image).
SPARE_LOCATIONS = 3

#: In a colour scene the part's colour proposes locations of its own, fitted
#: beside the first ones, and the alignment's further locations add less:
#: one spare, held to the bar of SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR
#: (LM-O ape, can, cat, 545 photos: with two spares at 0.6, AR_MSSD 0.142
#: -> 0.138, rec2D 0.272 -> 0.268 and 152 -> 165 ms median; one at 0.6,
#: 0.140 and 0.270; one at 0.7 is how colour scenes were fitted before).
SPARE_LOCATIONS_IN_COLOUR = 1
SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR = 0.7

#: A spare location is fitted only when its view search found at least this
#: share of the best location's evidence (SPARE_EVIDENCE_SHARE is the
#: alignment's gate before the search): ranked with EVIDENCE_WEIGHT, one with
#: less starts EVIDENCE_WEIGHT x (1 - share) behind (0.12) and practically
#: never wins. Hard bench set,
#: learning seeds 0-4, and paper set: identical accuracy, object-free paper
#: images with a detection 4 -> 3 of 10; hard seed 2, mean time per image
#: 61.1 -> 58.9 ms, 90th percentile 102 -> 85-95 ms (alternating runs).
#: LM-O ape, can, cat: AR identical (one can photo fewer in 2D). Replayed on
#: recorded fits, shares of 0.4-0.7 lost no right detection.
SPARE_MIN_VIEW_EVIDENCE_SHARE = 0.6

#: Weight of a location's view-search evidence, as a share of the best
#: fitted location's, in the ranking of fits without a colour cue (see
#: ``_ranked``).
EVIDENCE_WEIGHT = 0.3

#: Image-scale factors (inverse depth factors) of the extra starts of the
#: refinement when the first fit is poor.
DEPTH_STARTS = (1.08, 0.93, 1.16, 0.86)

#: Runners-up of the view search tried as extra starts of a poor first fit.
RUNNER_UP_STARTS = 2

#: Out-of-plane turn of the tilted restarts of a fit (:func:`_tilted_refit`),
#: degrees. The refinement's capture range in rotation is about 10°: from
#: the truth turned 5 / 10 / 15 / 20° (novel bench set, tee, clamp and
#: knob, every third image, three starts each) the full fit ended within 3°
#: of it in 0.90 / 0.68 / 0.43 / 0.31 of 126 fits, while the view search's
#: starts are up to about 10° off (its 162 views lie about 17° apart)
#: before the error of their in-plane turn.
TILT_DEG = 10.0

#: A tilted restart replaces the fit only when it ends at least this far
#: from it (degrees, the part's symmetries aside) and confirms at least
#: ``TILT_MIN_GAIN`` more of its contour: two fits a few tenths of a degree
#: or a hundredth of the contour apart are the same fit. Without these bars
#: (any gain counted) restarts replaced right fits with others a degree
#: off (5° starts: within 3° in 0.90 of the fits, as without restarts; with
#: them 0.94).
TILT_MIN_MOVE_DEG = 3.0
TILT_MIN_GAIN = 0.02

#: The axes of the tilted restarts: six in the image plane, 60° apart.
#: Four (the camera's x and y, each way) gave the same hard set and up to
#: 0.012 less AR_MSSD on the novel set (learning seeds 0-3: 0.865 / 0.882 /
#: 0.885 / 0.834 against 0.869 / 0.882 / 0.894 / 0.846), LM-O 0.137 / 0.191
#: against 0.139 / 0.191, for two quick fits fewer (pose stage about 1 ms).
_TILT_AXES = np.array([[math.cos(a), math.sin(a), 0.0]
                       for a in np.radians(np.arange(0.0, 360.0, 60.0))])

#: The tilted restarts' turns, :data:`TILT_DEG` about each of the
#: :data:`_TILT_AXES`, (6, 3, 3) camera-frame rotations.
_TILTS = np.asarray(Rotation.from_rotvec(np.radians(TILT_DEG) * _TILT_AXES).as_matrix())

#: Training views the view search returns per location: the first is fitted,
#: the others are the starts that compete with it (see ``_other_sides``).
VIEW_CANDIDATES = 6

#: The same for a part with near-symmetries (:mod:`viewloc_core.near_symmetry`):
#: its outline is nearly the same from several sides, so views far from the
#: best are as well confirmed as its neighbours, and the rival views that
#: the shading should judge lie beyond the best few (hard bench set,
#: free-form part, models learned with seeds 0/1/2: AR_MSSD 0.625, 0.585,
#: 0.510 -> 0.625, 0.610, 0.535 with 12; 12 for every part left the
#: L-bracket, which has none, as it was and cost 3 ms per image).
NEAR_SYMMETRIC_VIEW_CANDIDATES = 12

#: On a part with near-symmetries, the best this many short fits of the
#: rival starts (by :meth:`_Shading.rank`) get the full fit: a short fit's
#: rank says little about its full fit's (hard bench set, free-form part,
#: two images it was missed in: the starts that refined onto the truth were
#: 3rd-8th by their short fits). Hard bench set, models learned with seeds
#: 0/1/2, with the depth reversals: AR_MSSD 0.715, 0.688, 0.621 with 1;
#: 0.725, 0.695, 0.634 with 2; 0.725, 0.720, 0.634 with 3 (pose stage
#: +3 ms median over 1, before the shading agreement was compiled).
NEAR_SYMMETRIC_FULL_FITS = 3

#: ... unless its short fit ranks this far below the fit it competes with:
#: a near-symmetric part's rivals rank within hundredths of each other, and
#: one whose short fit confirms 15 % less of the contour is another outline,
#: not a rival (novel bench set, knob with a side lever: 42 % of those full
#: fits skipped, 12.3 -> 8.4 full fits and 44 -> 38 ms median pose stage per
#: image; hard set, learning seeds 0-4, and paper set: the same poses;
#: novel set, seeds 0-2: the same AR, three wrong knob poses moved; the same
#: AR at 0.2; at 0.1, 8 of the skipped full fits would have beaten the fit
#: they competed with, against 4 at 0.15).
NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP = 0.15

#: Rounds of rival starts (see ``_other_sides``): a rival that wins one has
#: its own twins and reversals tried in the next. Hard bench set, models
#: learned with seeds 0/1/2: AR_MSSD 0.725/0.720/0.634 with 1 round,
#: 0.750/0.726/0.646 with 2 (a third changed nothing at seed 0, measured
#: with extra starts turned about the least constrained axis, not kept).
OTHER_SIDE_ROUNDS = 2

#: Weight of the shading agreement (:mod:`viewloc_core.shading`, in [0, 1])
#: beside the share of the contour confirmed, when fits of different views at
#: one location compete: it decides between fits whose contours are
#: confirmed about equally, and cannot outweigh a contour that is clearly
#: better confirmed. A grey image shows fewer of the outline's edges than
#: the strongest of three colour channels, and there the share confirmed
#: tells a part from the part turned over less well: hard bench set in
#: grey, free-form part, the truth refined beside the wrong pose reported,
#: 4 of 5 wrong poses confirmed 0.6-5 % more of the outline, while their
#: shading agreed 0.02-0.12 less. AR_MSSD, learning seeds 0-4, 0.1 -> 0.2:
#: novel 0.8405 -> 0.8505 (no seed lower), hard in grey 0.7754 -> 0.7908,
#: hard 0.8862 -> 0.8837 (one image, right again once a losing runner-up's
#: turns are tried: see _other_sides), paper identical; 0.15 about the same
#: (0.8490, 0.7955, 0.8838); 0.3 lower on hard (seed 0 0.914 -> 0.899).
SHADING_WEIGHT = 0.2

#: The same for a part with a pattern of its own colours (a mesh with vertex
#: colours or a texture), whose shading cue reads the pattern too
#: (:mod:`viewloc_core.shading`) and so tells the part's sides apart more
#: surely. LM-O, learning seed 0, AR_MSSD / AR_MSPD, objects 1, 5, 6, 8
#: (without the pattern 0.139 / 0.191): weight 0.2 0.141 / 0.194, 0.4
#: 0.144 / 0.197, 0.7 0.147 / 0.201 (ape 0.153 -> 0.177), 1.0 0.148 /
#: 0.200, 1.5 0.147 / 0.198; held-out objects 9-12 (0.163 / 0.232): 0.2
#: 0.161 / 0.229, 0.7 0.163 / 0.232 (duck +0.016, hole puncher -0.021,
#: a dark part whose scanned colours vary little). The plain cue at 0.7
#: instead: 0.140 / 0.191 (ape 0.149) and 0.168 / 0.237.
PATTERNED_SHADING_WEIGHT = 0.7

#: Weight of the share of the edges inside a fit's silhouette that its
#: contour leaves unexplained (:mod:`viewloc_core.interior_edges`), taken
#: off the rank of fits of different views at one location: a part seen
#: from behind can show the same outline as from the front, and only the
#: true pose explains the creases inside it (novel bench set, the knob's
#: and the tee's reversed poses; learning seeds 0-4, AR_MSSD mean 0.8025 ->
#: 0.821, every seed better; at 0.1 about half the gain).
INTERIOR_EDGE_WEIGHT = 0.3

#: The interior-edge cue counts only for a part at least this share of
#: whose contour points are creases (:meth:`ContourModel.crease_share`). A
#: smooth part predicts no edge inside its outline, and its shading and
#: highlights are edges no pose explains: the cue then only adds noise (hard
#: bench set, whose free-form part has no crease: AR_MSSD 0.886/0.871/0.801
#: -> 0.831/0.819/0.746 at learning seeds 0/1/2 with the cue on every part,
#: all of it lost on that part; gated, 0.874 -> 0.876 over seeds 0-4). The
#: bench's machined parts have 12-33 % creases, LM-O's scanned ape and cat
#: 1.5 %, its can and driller 6.5 and 8.5 % (LM-O, every 2nd photo, AR_MSSD
#: 0.121 -> 0.120 with them gated in).
INTERIOR_EDGE_MIN_CREASE_SHARE = 0.05

#: Weight of the figure-ground contrast (:mod:`viewloc_core.figure_ground`)
#: beside the share of the contour confirmed, when fits at different
#: locations compete; a contrast of :data:`FIGURE_GROUND_FULL` or more counts
#: in full. A wrong place, a cast shadow or texture, encloses the colours
#: around it; the part usually does not (hard bench set, learning seeds 0-2,
#: 3-7 locations fitted per image: the right one ranked first in 209 of 240
#: by the contour alone, 216-220 with weights 0.05-0.2 and full counts of
#: 0.1-0.3).
FIGURE_GROUND_WEIGHT = 0.1
FIGURE_GROUND_FULL = 0.2

#: Candidates of a location with less evidence than this share of the best
#: one's (view search log-likelihood ratio) do not compete with its fit
#: (hard bench set: the right view, where it was a runner-up, had 0.79 to
#: 0.97 of the best one's evidence; the bar keeps the cost to close calls).
#: The view search's evidence ranks views less reliably than the fits'
#: ranking does, so the bar leaves room below that range: AR_MSSD over
#: learning seeds 0-4 at 0.75 -> 0.6, hard 0.8765 -> 0.8862 (no seed
#: lower), novel 0.8378 -> 0.8405; LM-O every 4th photo (AR_MSSD / MSPD)
#: 0.155 / 0.211 -> 0.153 / 0.215, held-out objects 9-12 every 2nd photo
#: 0.136 / 0.210 -> 0.138 / 0.212. About 4 more short fits per hard image
#: (21 -> 25).
OTHER_VIEW_EVIDENCE_SHARE = 0.6

#: Candidates from the other side of the part each location's view search
#: adds after its best (``search_views(other_side=...)``) for a part with
#: colours of its own whose surface is known (:func:`_compares_sides`).
#: Every candidate that sees the other side of the fit's view is tried as a
#: rival start whatever its evidence: on real photos the contour can prefer
#: one side throughout the search while the fitted shading and colour tell
#: the sides apart.
#: LM-O ape at the right place and the wrong side (36 photos): the
#: location's candidates lay 100-180° from the truth in most, while a fit
#: started from the truth outranked the chosen one in 27; and in 21 of 21
#: photos checked, the truth fitted outranked the truth turned over and
#: fitted.
OTHER_SIDE_CANDIDATES = 1

#: Candidates whose start is within this rotation (deg, over the part's
#: symmetries) of the fit already made are not fitted again.
DISTINCT_VIEW_DEG = 20.0

#: The wider look at a reported detection's location (:func:`_wider_look`):
#: the views its view search screens and returns, and how many of the
#: location's candidates seed it. LM-O, learning seed 0, AR_MSSD / AR_MSPD
#: with 40 and 20: objects 1, 5, 6, 8 0.157 / 0.217, held-out 9-12 0.180 /
#: 0.251; with 60 and 30: 0.159 / 0.220 and 0.178 / 0.251 (the same within
#: the runs' noise, for more fits). Its rival views are started nearer and
#: farther too, as a location's are (RIVAL_SCALE_FACTORS): at their searched
#: scale alone 0.152 / 0.213 and 0.175 / 0.252, pose stage 11-21 ms shorter.
WIDER_SCREENED_VIEWS = 40
WIDER_VIEW_CANDIDATES = 20
WIDER_LOOK_SEEDS = 3

#: Factors on a rival view's image scale at which it is also started (see
#: :func:`_best_rival`): nearer and farther by about an eighth. The view
#: search's scale is uncertain by about that much (its grid steps 7%, the
#: colour locations' seeds 25%; on real photos the templates' inner edges
#: are not the photo's), and a short fit started that far off in depth does
#: not get there (LM-O ape, the right view 11° off at 14% too large a
#: scale: its short fit ended 78 mm off and confirmed 0.68 of the contour,
#: the truth's fit 0.91, and a view 160° off won). AR_MSSD, learning seeds
#: 0-4, against none: novel 0.8408 / 0.8692 / 0.8525 / 0.8167 / 0.81 (mean
#: 0.8378) against 0.8408 / 0.8492 / 0.8483 / 0.8158 / 0.8033 (0.8315);
#: hard 0.9013 / 0.8725 / 0.8175 / 0.8975 / 0.8938 against 0.895 / 0.8787
#: / 0.8175 / 0.885 / 0.9062 (0.8765 both). LM-O, seed 0, every 4th photo:
#: 0.149 / 0.201 -> 0.155 / 0.211 (AR_MSSD / AR_MSPD); held-out objects
#: 9-12, every 2nd photo: 0.131 / 0.205 -> 0.136 / 0.210. Only the best
#: rival view at other depths: novel 0.8335, hard unchanged; the first
#: fit's own view at other depths as well: novel 0.8373, hard 0.8745. The
#: cost: about 7 more short fits per image on the hard set (14 -> 21).
RIVAL_SCALE_FACTORS = (0.88, 1.14)


#: Image locations the part's colour proposes (:mod:`viewloc_core.part_colour`;
#: models that know their part's colours, colour scenes, refinement on: only
#: a fit says whether the part's colours cover its surface), searched and
#: fitted beside the alignment's. On real photos the alignment seldom
#: proposes a small or dull part (LM-O ape, every 3rd photo: the truth was
#: among the fitted places in 28 of 59, and in 11 of the other 31 a fit
#: started from the truth would have ranked first), and the colour's
#: windows put it 4th-9th in 9 of 59. Whole LM-O sets, learning seed 0,
#: AR_MSSD / AR_MSPD / median latency with 3, 4 and 5 locations: objects
#: 1, 5, 6, 8 0.128 / 0.175 / 137 ms, 0.134 / 0.188 / 151 ms, 0.137 /
#: 0.196 / 170 ms (ape, can and cat each better with each); held-out
#: objects 9-12 0.152 / 0.217 / 142 ms, 0.161 / 0.229 / 158 ms, 0.160 /
#: 0.227 / 174 ms. The fifth is not worth its 20 ms. hard-photos (learned
#: from photos, so with a colour cue), 4 or 5 locations: the same poses.
#: Later, with the colour's outline searched too, 4 -> 8 locations: objects
#: 1, 5, 6, 8 0.188 / 0.260 -> 0.200 / 0.278, held-out 0.191 / 0.273 ->
#: 0.195 / 0.280, but part-free photos with a detection 8 -> 13 of 18 and
#: 59 -> 65 of 65 (more places, more chance fits) and the held-out photos'
#: median latency +29 % (both runs three at once).
COLOUR_LOCATIONS = 4

#: Square windows of the colour proposals: half their side as a share of
#: the part's image diameter (the part's middle, whatever its shape), over
#: this many sizes spanning the alignment's scale range.
COLOUR_WINDOW_SHARE = 0.25
COLOUR_WINDOW_SIZES = 16

#: A colour proposal is a place for the part: the next one is centred at
#: least the part's radius (at the window's scale) from it on either axis,
#: i.e. this many window half sides. Kept outside the window alone (one
#: half side), a region of the part's colours larger than the part (a
#: wooden surface, another object of like colour) took every proposal in
#: turn while a smaller or partly hidden part went unproposed: half-hidden
#: LM-O apes, all four proposals 3-7 diameters off in 5 photos, the second
#: one on the ape in 4 of them. Learning seed 0, AR_MSSD / AR_MSPD: LM-O
#: objects 1, 5, 6, 8 0.187 / 0.260 -> 0.189 / 0.269 (rec2D 0.290 ->
#: 0.301; ape and can up, cat -0.006), held-out objects 10 and 11 (egg box,
#: glue) 0.070 / 0.098 -> 0.091 / 0.126 (rec2D 0.106 -> 0.141); part-free
#: photos with a detection 8 -> 12 of 18 and 48 -> 50 of 53 (more distinct
#: places, more chance fits); pose stage +30 % on objects 1, 5, 6, 8, total
#: latency +9 % on the held-out ones (runs two at a time). Parts without
#: colours make no colour proposals.
COLOUR_PROPOSAL_EXCLUSION = 0.5 / COLOUR_WINDOW_SHARE

#: Seeds of the view search at a colour location: in-plane angles (deg)
#: and factors of the scale the window's size suggests (it says the size
#: only roughly: the part's colour may cover part of it).
COLOUR_SEED_ANGLES_DEG = tuple(range(0, 360, 15))
COLOUR_SEED_SCALES = (0.8, 1.0, 1.25)

#: The colour says the part's centre to about 0.1 of its diameter, more
#: than the view search's spread map tolerates (2 px): its seeds are also
#: screened on a grid of offsets reaching this share of the diameter each
#: way (:func:`_colour_offsets`), and the best ``COLOUR_KEPT_SEEDS`` of them
#: get the full angle and scale grid.
#: The screen tries the seeds' own angles only: 15° apart, they are within
#: the ±11° the spread orientation map accepts, and each position then
#: costs a third of the plain screen's three angles.
COLOUR_OFFSET_SHARE = 0.1
COLOUR_KEPT_SEEDS = 24
COLOUR_SCREEN_ANGLES_DEG = (0.0,)


def _colour_offsets(reach_px: float) -> NDArray[np.float64]:
    """The offsets at which a colour location's seeds are screened, (O, 2)
    search-level pixels: a square grid over ``reach_px`` each way, as few
    steps as leave every point of the square within the view fit's first
    reach (:data:`viewloc_core.view_search.FIT_RADII_PX`) of an offset.

    Three by three for a part up to about 57 px across on the searched
    level (0.1 of its diameter each way), five by five up to about 113 px,
    and so on: at three by three a large part's nearest offset lay beyond
    the fit's reach of its centre (LM-O's driller, 150 px across: offsets
    15 px apart, and its true view at the true place, which explains the
    edges better than any view the search found there, never seeded).
    LM-O, learning seed 0, the same models both ways, every photo: found
    in 2D 229 -> 233 of 745 targets (+11 -7), AR_MSSD (per-target mean
    over the bench's thresholds) 0.192 -> 0.202 (ape 0.274 -> 0.285, can
    0.151 -> 0.169, driller 0.013 -> 0.024, cat the same); held-out
    objects 9-12, every 2nd photo, 117 -> 123 of 348, 0.206 -> 0.218 (hole
    puncher 0.238 -> 0.266), part-free photos with a detection 33 -> 32 of
    36. Median latency, every 8th photo, alone: 269 -> 282 ms; the can's
    298 -> 375 and the driller's 197 -> 258 (5x5 and 7x7 offsets), the
    ape's and cat's as before.
    """
    half_steps = max(1, math.ceil(reach_px / (FIT_RADII_PX[0] * math.sqrt(2.0))))
    steps = np.linspace(-reach_px, reach_px, 2 * half_steps + 1)
    return np.array([(dx, dy) for dy in steps for dx in steps], np.float64)


#: Views searched at a colour location on the outline of the part's colour
#: as well as on the photo's edges (:attr:`_Located.colour_rivals`). In
#: clutter the photo's edges mislead the view search (LM-O ape, 7 photos
#: whose fits lay at the colour's place but 0.15-0.24 of the part's
#: diameter beside it and turned over by 117-171°: the views within 30° of
#: the truth ranked beyond the 40th or were not among the 40 at all, while
#: the fit refined from the truth ranked higher by :meth:`_Shading.rank`);
#: the colour's outline leaves the clutter out, and put such a view among
#: its first six in 4 of the 7. Learning seed 0, LM-O objects 1, 5, 6, 8,
#: AR_MSSD / AR_MSPD 0.157 / 0.217 -> 0.190 / 0.262 with six, 0.185 /
#: 0.257 with three (views and pose stages +30 and +31 ms median with six,
#: two runs at once; three saved 12 ms of the pose stage).
COLOUR_OUTLINE_CANDIDATES = 6

#: A colour location whose best view explains the edges there no better
#: than clutter does (log likelihood ratio at most this) is not fitted,
#: unless the part's colours are rare in the scene (COLOUR_OUTLINE_MIN_RARITY)
#: and a view explains the outline of its colour there better than that.
COLOUR_MIN_EVIDENCE = 0.0

#: Weight of the relative colour agreement (mean P(part | colour) under
#: the fit's visible surface over what the part's own colours get in the
#: scene, about 1 on the part; :attr:`_Fitted.relative_colour`) beside the
#: share of the contour confirmed when fits of different locations compete:
#: on real photos in clutter, fits at wrong places confirm as much of their
#: contour as right ones.
COLOUR_WEIGHT = 1.0

#: Fits whose visible surface the part's colours explain less than this
#: (mean posterior; 0.5 is a colour as likely the part's as the scene's)
#: are not reported.
MIN_COLOUR_AGREEMENT = 0.35

#: Nor are fits whose share of the contour confirmed plus
#: ``COLOUR_WEIGHT`` times their relative colour agreement (the rank colour
#: fits compete by) falls under this: a fit the refinement accepts (0.6 of
#: its contour found) must show the colours the part itself shows in the
#: scene, a fit with less of them more contour. Relative, because what a
#: part shows of its colours depends on how common they are in the scene
#: (LM-O, all photos: right fits' agreement 0.58-0.69 for the can, whose
#: own colours get 0.62 in those scenes, 0.74-0.93 for the ape, 0.92): an
#: absolute bar (1.4) dropped most right fits of the can and kept the ape's
#: look-alikes.
MIN_COLOUR_RANK = 1.6

#: A part hides what lies behind it, so its colours end at its outline:
#: where they run on beyond a fit's outline, the fit lies beside the part
#: (shifted onto the part of it that shows) or on a larger region of its
#: colours. That share (:attr:`_Fitted.colour_leak`: the mean posterior in
#: the ring just outside the outline, figure_ground's, over the agreement
#: the part's own colours get in the scene) lowers the key colour fits of
#: different places are ranked by (:func:`_ranked`) by COLOUR_LEAK_WEIGHT
#: times its excess over COLOUR_LEAK_FLOOR, in proportion to how rare the
#: part's colours are in the scene (``2 * expected - 1``, clipped to
#: 0..1: around a part of common colours, a white can on a white board,
#: the ring is part-like whether the fit is right or not). It orders fits
#: only (beyond COLOUR_LEAK_MAX the fit is dropped, below); the colour
#: gates (MIN_COLOUR_AGREEMENT, MIN_COLOUR_RANK) read the plain rank.
#: LM-O, learning seed 0, reported fits (every 2nd photo): the cat's
#: right ones 0.24-0.35 (10th-90th percentile), wrong ones 0.35-0.62; the
#: ape's right 0.13-0.36, wrong 0.16-0.36; the can's and
#: the driller's 0.63-0.96 right or wrong. Taken into the colour
#: agreement instead (the gates too), the ring cost right fits: cat rec2D
#: 0.52 -> 0.44, the can 0.25 -> 0.05 unweighted. As a ranking term, AR_MSSD
#: / AR_MSPD: objects 1, 5, 6, 8, learning seed 0, 0.1887 / 0.2683 ->
#: 0.1899 / 0.2703 (3 more cats right, none lost), seed 1 0.1846 / 0.2517
#: -> 0.1863 / 0.2548 (2 more cats); held-out objects 9-12 0.202 / 0.280
#: -> 0.205 / 0.284 (egg box +1, hole puncher +2 and -1); part-free photos
#: with a detection unchanged (12 of 18, 61 of 65). One ring per fitted
#: place: about 0.85 ms, 5 an LM-O photo.
COLOUR_LEAK_FLOOR = 0.35
COLOUR_LEAK_WEIGHT = 1.0

#: Where the part's colours are rare in the scene (rarity ``2 * expected -
#: 1`` at least COLOUR_LEAK_MIN_RARITY: the part's own colours get an
#: agreement of 0.75 or more), a fit with COLOUR_LEAK_MAX or more of that
#: agreement in the ring just outside its outline lies on or beside a
#: region of the part's colours larger than itself, not on the part, and is
#: not reported (:func:`_ranked`). LM-O photos, learning seed 0, every
#: refined fit of every target photo (objects 1, 5, 6, 8 and held-out 9-12):
#: the right fits' leaks of the parts of rare colours (ape, cat, duck, hole
#: puncher; rarity 0.5-0.84) lay under 0.38-0.47 (97th percentile by part),
#: at most 0.47-0.60; of their wrong fits 2-34 % lay at 0.5 or more (the
#: cat 34 %, the hole puncher 27 %). Around parts of common colours (the
#: can, egg box, glue, driller: rarity 0.13-0.25) right fits leak 0.59-0.81
#: (the median): no gate there. make bench, LM-O, learning seed 0: wrong
#: detections on photos of the part, cat 47 -> 30 of 139, hole puncher
#: 81 -> 71 of 167, duck 63 -> 62; right ones lost: one hole puncher of
#: the 1,445 targets; part-free photos with a detection unchanged (12 of
#: 18, 61 of 65); AR_MSSD / AR_MSPD 0.1899 / 0.2703 -> 0.1899 / 0.2701,
#: held-out 0.2013 / 0.2884 -> 0.2013 / 0.2876. Learning seed 1: cat
#: 41 -> 22 of 128, ape 83 -> 80, no right one lost; 0.1859 / 0.2540 ->
#: 0.1852 / 0.2532 (a dropped ape 28 mm off had counted at the loosest
#: thresholds).
COLOUR_LEAK_MAX = 0.5
COLOUR_LEAK_MIN_RARITY = 0.5

#: Where the part's colours are rare in the scene (the rarity of
#: COLOUR_LEAK_MIN_RARITY: an agreement of 0.75 or more for its own
#: colours), the outline of its colour is the part's outline, and a colour
#: location whose photo edges explain no view (COLOUR_MIN_EVIDENCE) is
#: searched on that outline instead (:attr:`_Located.outline_only`); its
#: fit, with no support from the photo's edges, is held to the spares' bar
#: (:func:`_supported`). A blurred part, or one as bright as what lies
#: around it, shows few edges of its own: LM-O cat, every 4th photo, the
#: colour proposed the truth's place in 36 of 43, and at 5 of those the
#: best view on the photo's edges explained them no better than clutter
#: (evidence -24 to -2; the truth's nearest views found 27-45 % of their
#: edge samples in the two looked at, a pale blurred cat on grey). Every
#: photo, learning seed 0, the same models both ways: cat found in 2D 92 ->
#: 94 of 171, none lost, no detection added elsewhere; ape, can, driller
#: unchanged. Without the spares' bar the cat gained 4 but got 4 wrong
#: detections where it had none (and the ape 1); around parts of common
#: colours (LM-O can, egg box, glue, driller: agreements 0.56-0.65) the
#: colour's outline runs through clutter of like colours, and searched
#: there it gave the driller 15 wrong detections where it had none and no
#: right one.
COLOUR_OUTLINE_MIN_RARITY = COLOUR_LEAK_MIN_RARITY

#: A refined fit whose rotation its contour leaves this uncertain (the
#: largest standard deviation over all axes, degrees, a continuous
#: symmetry's turn set aside; :mod:`viewloc_core.pose_determinacy`) is not
#: a pose, and is not reported unless the request allows more
#: (``LocalizeOptions.max_rotation_std_deg``). Image edges along one side of
#: an outline, or an outline that looks the same turned, confirm a fit as
#: well as the part does: on the bench's part-free images the refined top
#: fits' largest deviations were 14-73° in 14 of 24 (paper, hard, novel; a
#: rounded distractor taken for the free-form part, a clutter stick for the
#: barbell's bar), where right fits' 95th percentile was 1-7° by part (the
#: knob 11°; LM-O's ape, small in real clutter, 10°). At 30° (make bench,
#: learning seed 0) images without the part that got a detection: paper 4
#: -> 3 of 10, hard 10 -> 7 of 12, novel 12 -> 11 of 12, hard-photos 11 ->
#: 7 of 12, LM-O 11 -> 9 of 18, held-out LM-O objects 62 -> 61 of 65; every
#: AR the same (LM-O AR_MSPD +0.0001). At 20° more went (paper 3, hard 6,
#: novel 10, hard-photos 6, LM-O 8) but real photos lost right places fitted
#: turned over (held-out LM-O: duck 6 and hole puncher 5 fewer 2D-right
#: detections, AR_MSSD / AR_MSPD 0.1647 / 0.2369 -> 0.1626 / 0.2333); at 15°
#: LM-O lost two ape poses within 11° of the truth.
MAX_ROTATION_STD_DEG = 30.0


@dataclass(frozen=True, slots=True)
class LocalizeOptions:
    """Per-request options (API: ``options``).

    Attributes
    ----------
    max_detections : int
        Most detections returned (1..100).
    min_score : float or None
        Minimum score in [0, 1]; None uses the model's default.
    refine : bool
        Refine poses against image edges when the model has a mesh.
    roi : ImageRegion or None
        The image region the part's centre lies in; None for anywhere.
    depth_mm : DepthRange or None
        The depths the part's origin can have; None for any.
    max_rotation_std_deg : float or None
        The most rotation uncertainty (degrees, > 0) a refined detection
        may have (see MAX_ROTATION_STD_DEG); None uses that default.
    timeout_ms : float or None
        Time budget of the localization, ms (> 0), counted from its start
        (features included); None for none. A search that only looks
        further for the part (the finer level's, spare locations', further
        locations') is started only when it is expected to end within it
        (see :func:`localize_in_scene`); a search begun is finished, so the
        answer can come later than the budget when one took longer than
        expected.
    """

    max_detections: int = 1
    min_score: float | None = None
    refine: bool = True
    roi: ImageRegion | None = None
    depth_mm: DepthRange | None = None
    max_rotation_std_deg: float | None = None
    timeout_ms: float | None = None

    def __post_init__(self) -> None:
        if not 1 <= self.max_detections <= 100:
            raise InvalidInputError("must be in 1..100", "options.max_detections")
        if self.min_score is not None and not 0.0 <= self.min_score <= 1.0:
            raise InvalidInputError("must be in [0, 1]", "options.min_score")
        if self.max_rotation_std_deg is not None and not (
                math.isfinite(self.max_rotation_std_deg) and self.max_rotation_std_deg > 0):
            raise InvalidInputError("must be a positive number of degrees",
                                    "options.max_rotation_std_deg")
        if self.timeout_ms is not None and not (
                math.isfinite(self.timeout_ms) and self.timeout_ms > 0):
            raise InvalidInputError("must be a positive number of milliseconds",
                                    "options.timeout_ms")

    def deadline(self, start: float) -> float:
        """The :func:`time.perf_counter` time at which the budget of a
        localization begun at ``start`` is spent (infinite without one)."""
        return math.inf if self.timeout_ms is None else start + self.timeout_ms / 1e3

    @property
    def rotation_std_limit_deg(self) -> float:
        """The rotation uncertainty a refined detection may have, degrees."""
        return (MAX_ROTATION_STD_DEG if self.max_rotation_std_deg is None
                else self.max_rotation_std_deg)


@dataclass(frozen=True, slots=True)
class LocalizationResult:
    """Detections, best first, where the time went (ms), and whether a
    search was left out for the time budget (``LocalizeOptions.timeout_ms``)."""

    detections: list[Detection]
    timing_ms: dict[str, float] = field(default_factory=dict)
    timed_out: bool = False


#: Threads that build the refinement's edge pyramid while the alignment runs
#: (two, as features' LSD pool: concurrent requests need not queue).
_EDGE_POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="viewloc-edges")


@dataclass(eq=False)
class Scene:
    """What localizing any part in one image starts from, done once
    (:func:`prepare_scene`): a request for several parts in one image
    shares it (:func:`localize_in_scene`) instead of finding the same
    features and building the same edge pyramid for each.

    Attributes
    ----------
    image : (H, W) or (H, W, 3) array
        The scene as the pipeline reads it: a colour image without colours
        as one channel (:func:`_one_channel_if_grey`).
    camera : Camera
        Its intrinsics.
    factor : float
        Search-level pixels per image pixel, at most 1.
    level : array
        The image at the search level (long side at most
        :data:`MAX_SEARCH_SIDE_PX`).
    features : ImageFeatures
        The search level's features.
    chance : ChanceRates
        The search level's clutter model, for the alignment and the view search.
    features_ms : float
        What the features took, ms.
    """

    image: NDArray[Any]
    camera: Camera
    factor: float
    level: NDArray[Any]
    features: ImageFeatures
    chance: ChanceRates
    features_ms: float
    #: The pyramid's job, None until asked for when not started up front.
    _edges: Future[EdgePyramid] | None = field(default=None, repr=False)
    _edges_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)
    #: The scene searched on the finer level (:meth:`at_finer_level`),
    #: None until a part asks for it.
    _finer: Scene | None = field(default=None, repr=False)
    _finer_lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    def has_finer_level(self) -> bool:
        """Whether :meth:`at_finer_level` searches a finer level than this
        scene's (an image larger than :data:`MAX_SEARCH_SIDE_PX`)."""
        return _level_factor(self.image, FINER_SEARCH_SIDE_PX) > self.factor

    def at_finer_level(self) -> Scene:
        """The scene searched on a finer pyramid level, whose long side is
        at most :data:`FINER_SEARCH_SIDE_PX` (the image itself when it is
        that small), or itself when its level is that fine already. Its
        features are found once, when a part first asks for them
        (:func:`localize_in_scene`), and it shares this scene's edge
        pyramid."""
        if not self.has_finer_level():
            return self
        with self._finer_lock:
            if self._finer is None:
                with self._edges_lock:
                    edges = self._edges
                self._finer = _searched_scene(
                    self.image, self.camera, _level_factor(self.image, FINER_SEARCH_SIDE_PX),
                    edges)
            return self._finer

    def edges(self) -> EdgePyramid:
        """The refinement's edge pyramid of the image: the one started by
        :func:`prepare_scene`, or built now when it was not asked for."""
        with self._edges_lock:
            if self._edges is None or self._edges.cancelled():
                self._edges = _EDGE_POOL.submit(
                    prepare_edges, self.image,
                    _refine_levels(self.image.shape[1], self.image.shape[0]))
            job = self._edges
        return job.result()

    def release(self) -> None:
        """Stop the edge pyramid if no fit has asked for it and it has not
        started (a pool busy with other requests): nothing to refine."""
        with self._edges_lock:
            if self._edges is not None:
                self._edges.cancel()
        with self._finer_lock:
            if self._finer is not None:
                self._finer.release()


def refines(model: ObjectModel, options: LocalizeOptions) -> bool:
    """Whether ``model``'s fits are refined on the image's edges: when the
    request asks for it and the model has a mesh's contours."""
    return options.refine and model.contour is not None


def prepare_scene(image: NDArray[np.generic], camera: Camera, edges: bool = True) -> Scene:
    """The part-independent start of a localization in ``image``.

    Parameters
    ----------
    image : (H, W) or (H, W, 3) array, uint8 or uint16
        The scene (RGB when colour).
    camera : Camera
        Intrinsics of the scene camera; its width and height must match the image.
    edges : bool
        Start building the refinement's edge pyramid now, on another core
        (OpenCV releases the GIL), so that it is ready when the first fit
        needs it; False when nothing will be refined.

    Returns
    -------
    Scene
    """
    arr = np.asarray(image)
    if arr.ndim not in (2, 3) or arr.shape[0] != camera.height or arr.shape[1] != camera.width:
        raise InvalidInputError(
            f"image is {arr.shape[1] if arr.ndim >= 2 else '?'}x{arr.shape[0]}, camera says "
            f"{camera.width}x{camera.height}", "camera",
        )
    to_grey_float(arr[:16, :16])  # dtype and channel checks, cheap
    arr = _one_channel_if_grey(arr)
    scene = _searched_scene(arr, camera, _level_factor(arr, MAX_SEARCH_SIDE_PX), None)
    if edges:
        # The pyramid needs nothing but the image: it is built on the other
        # core while alignment and view search run (only the levels the
        # refinement uses, the same for its final and quick fits).
        scene._edges = _EDGE_POOL.submit(prepare_edges, arr,
                                         _refine_levels(arr.shape[1], arr.shape[0]))
    return scene


def _level_factor(image: NDArray[Any], max_side_px: int) -> float:
    """Level pixels per image pixel of the pyramid level whose long side
    is at most ``max_side_px``; 1 for an image no larger."""
    return min(1.0, max_side_px / max(image.shape[0], image.shape[1]))


def _searched_scene(image: NDArray[Any], camera: Camera, factor: float,
                    edges: Future[EdgePyramid] | None) -> Scene:
    """A scene searched on the level ``factor`` of ``image`` (its features
    found now), with the refinement's edge pyramid job ``edges``."""
    level = image
    if factor < 1.0:
        level = cv2.resize(image, (round(image.shape[1] * factor),
                                   round(image.shape[0] * factor)),
                           interpolation=cv2.INTER_AREA)
    t0 = time.perf_counter()
    feats = extract_features(level)
    features_ms = (time.perf_counter() - t0) * 1e3
    return Scene(image, camera, factor, level, feats, chance_rates(feats), features_ms, edges)


_INDEX_CACHE: weakref.WeakKeyDictionary[ObjectModel, ModelIndex] = weakref.WeakKeyDictionary()


def warm_up() -> None:
    """Compile the pipeline's numba kernels now (a service calls this at
    start-up, so that no request waits for the compiler)."""
    feature_kernels.warm_up()
    near_pairs.warm_up()
    similarity_fit.warm_up()
    seeding.warm_up()
    pairing.warm_up()
    sample_evidence.warm_up()
    colour_kernels.warm_up()
    normal_search.warm_up()
    contour_kernels.warm_up()
    gauss_newton_kernel.warm_up()
    refine_kernels.warm_up()
    shading_kernels.warm_up()
    shift_search.warm_up()


def prepare(model: ObjectModel) -> None:
    """Build everything :func:`localize` derives from a model once (the
    alignment index, the view-search templates, the contour model, the surface
    samples and near-symmetries), so that the first localization of the model
    is as fast as the rest.

    Without this the first request pays for them: about 0.3-1.0 s for the
    bench parts (0.2-0.4 s of it the templates' sample classes). The results
    are cached per model object while it lives, as when a localization builds
    them.
    """
    model_index(model)
    view_templates(model)
    _contour_model(model)
    _surface(model)


def model_index(model: ObjectModel) -> ModelIndex:
    """The alignment index of a model, built once and cached while the model lives."""
    return cached_per_model(_INDEX_CACHE, model, build_index)


_CONTOUR_CACHE: weakref.WeakKeyDictionary[ObjectModel, ContourModel] = (
    weakref.WeakKeyDictionary()
)


_SURFACE_CACHE: weakref.WeakKeyDictionary[
    ObjectModel, tuple[SurfaceSamples, NearSymmetries]] = weakref.WeakKeyDictionary()


def _surface(model: ObjectModel) -> tuple[SurfaceSamples, NearSymmetries] | None:
    """Surface samples of the model's mesh in the centred frame poses are
    fitted in, and the part's near-symmetries found on them (None without a
    mesh), cached."""
    if model.mesh_vertices_mm is None or model.mesh_faces is None or not len(model.mesh_faces):
        return None
    faces = model.mesh_faces

    def build(m: ObjectModel) -> tuple[SurfaceSamples, NearSymmetries]:
        vertices = np.asarray(m.mesh_vertices_mm, np.float64) - m.origin_offset_mm
        mesh = trimesh.Trimesh(vertices, np.asarray(faces, np.int64), process=False)
        return (surface_samples(vertices, faces, vertex_colours=m.mesh_vertex_colours),
                near_symmetries(mesh, m.symmetry_group()))

    return cached_per_model(_SURFACE_CACHE, model, build)


def _contour_model(model: ObjectModel) -> ContourModel | None:
    """The model's contour model for refinement (None without a mesh), cached."""
    if model.contour is None:
        return None
    arrays = model.contour
    return cached_per_model(_CONTOUR_CACHE, model, lambda _: ContourModel.from_arrays(arrays))


def _refit_at_model_scale(
    model: ObjectModel, t_view: int, sim: NDArray[np.float64], image: NDArray[np.generic],
    radius_px: float,
) -> tuple[NDArray[np.float64], float]:
    """Final 2D fit of a training view on a crop resampled to training scale.

    Returns the re-fitted similarity training-view frame -> image and its coverage.
    """
    tr = model.training
    pts = tr.edge_xy[t_view].astype(np.float64)
    theta = tr.edge_theta[t_view].astype(np.float64)
    refit, crop_feats, crop_from_image = refine_at_model_scale(image, sim, pts, theta, radius_px)
    cov = coverage(crop_feats, sim2.compose(crop_from_image, refit), pts, orientation_bin(theta))
    return refit, cov


def _to_full_resolution(sim_level: NDArray[np.float64], factor: float) -> Similarity2D:
    """A similarity found on a pyramid level scaled by ``factor``, in full-resolution pixels."""
    sim_full = sim_level.copy()
    if factor < 1.0:
        sim_full[:2] = (sim_level[:2] + 0.5) / factor - 0.5
        sim_full[3] = sim_level[3] / factor
    return sim2.to_similarity2d(sim_full)


def _one_channel_if_grey(image: NDArray[Any]) -> NDArray[Any]:
    """A colour image without colours (:func:`part_colour.is_grey_in_colour`)
    as the (H, W) maximum of its channels, the grey the features see; any
    other image as it is.

    A monochrome camera's frames often come stored as RGB. Taken as colour,
    their chromaticity is flat everywhere: every fit's figure-ground contrast
    is 0, so no first fit is ever settled and every image pays for spare
    fits, and the colour gradients cost three channels for one. Bench set
    hard-mono (the hard set's luminance stored as RGB), learning seed 0:
    AR_MSSD / AR_MSPD 0.729 / 0.761 with a pose stage of 53.8 ms median when
    taken as colour, 0.749 / 0.780 and 32.0 ms as grey.
    """
    if image.ndim == 3 and part_colour.is_grey_in_colour(image):
        # Channel planes: numpy's reduction over a trailing axis of 3 costs
        # several times more (a 5 MP frame).
        return np.maximum(np.maximum(image[..., 0], image[..., 1]), image[..., 2])
    return image


def _pose_centred(
    model: ObjectModel, t_view: int, similarity: Similarity2D, camera: Camera
) -> Pose:
    """6D pose of the model's centred frame from a training view's similarity (§4.2)."""
    return pose_from_similarity(
        similarity, model.training.R_m2c[t_view], model.d0_mm, model.f_train_px, camera
    )


@dataclass(frozen=True, slots=True)
class _FitOptions:
    """The refinements of one location (full, quick and twin fits), all with
    the weakest edge its surroundings call for (:mod:`viewloc_core.edge_contrast`),
    so that the fits compared there count inliers alike."""

    final: RefineOptions = FINAL_REFINE
    quick: RefineOptions = QUICK_REFINE
    twin: RefineOptions = TWIN_REFINE

    @classmethod
    def near(cls, edges: EdgePyramid, camera: Camera, pose: Pose,
             diameter_mm: float) -> _FitOptions:
        """The options for a part near ``pose`` (object centre in front of the
        camera), on all of the pyramid's levels (see :func:`_refine_levels`)."""
        z = float(pose.t_m2c[2])
        centre = camera.project(pose.t_m2c[None])[0]
        floor = local_min_gradient(edges, (float(centre[0]), float(centre[1])),
                                   0.5 * camera.fx * diameter_mm / z, FINAL_REFINE.min_gradient)
        return cls(*(_on_levels(replace(o, min_gradient=min(o.min_gradient, floor)),
                                edges.levels)
                     for o in (FINAL_REFINE, QUICK_REFINE, TWIN_REFINE)))


def _refine_levels(width: int, height: int) -> int:
    """Pyramid levels of the refinements for an image of this size:
    ``FINAL_REFINE.levels``, and one more for each doubling of the long side
    beyond :data:`REFINE_REFERENCE_SIDE_PX` (at most 5)."""
    doublings = round(math.log2(max(width, height) / REFINE_REFERENCE_SIDE_PX))
    return min(5, FINAL_REFINE.levels + max(0, doublings))


def _on_levels(options: RefineOptions, levels: int) -> RefineOptions:
    """``options`` started on ``levels`` pyramid levels: each level it has
    too few of searches and iterates as its coarsest does, and the start's
    shift search reaches as many more full-resolution pixels as the extra
    levels halve (the same reach on the coarsest level); ``options`` as
    they are for their own number of levels or fewer."""
    extra = levels - options.levels
    if extra <= 0:
        return options
    return replace(options, levels=levels,
                   search_px=options.search_px + (options.search_px[-1],) * extra,
                   iterations=options.iterations + (options.iterations[-1],) * extra,
                   shift_search_px=options.shift_search_px * 2.0 ** extra)


def _rarity(expected_agreement: float) -> float:
    """How rare the part's colours are in a scene, 0..1: ``2 * expected -
    1`` of the agreement they get there (:func:`part_colour.expected_agreement`),
    0 for colours as likely the scene's as the part's."""
    return min(max(2.0 * expected_agreement - 1.0, 0.0), 1.0)


@dataclass(frozen=True, slots=True, eq=False)
class _Fitted:
    """A location's detection and how well its refinement was confirmed.

    Attributes
    ----------
    detection : Detection
    chance_corrected : float or None
        The refinement's inlier fraction corrected for the chance rate of
        the image around it (:attr:`RefinementResult.score`); None when
        the pose was not refined.
    colour_agreement : float or None
        Mean P(part | colour) under the pose's visible surface
        (:meth:`_ColourScene.agreement`); None without a colour cue.
    expected_colour_agreement : float or None
        The agreement the part's own colours get in the scene
        (:attr:`_ColourScene.expected_agreement`); None without a colour cue.
    figure_ground : float or None
        Chromaticity contrast between the pose's visible surface and its
        surroundings (:func:`figure_ground_contrast`); None without the
        part's surface or colour in the image.
    evidence : float
        The view search's log-likelihood ratio of the location's best view
        (:attr:`_Located.evidence`).
    rotation_std_deg : float or None
        The refined pose's largest rotation uncertainty, degrees
        (:func:`viewloc_core.pose_determinacy.rotation_std_deg`); None when
        the pose was not refined.
    location_fit : _LocationFit or None
        The refinement the detection was judged from, to take up again
        (:func:`_wider_look`); None without refinement.
    colour_leak : float or None
        Mean P(part | colour) just outside the pose's outline over the
        agreement the part's own colours get in the scene
        (:meth:`_ColourScene.leak`); None without a colour cue or with too
        little of that ring in the image (then neither ranks nor gates it).
    """

    detection: Detection
    chance_corrected: float | None = None
    colour_agreement: float | None = None
    figure_ground: float | None = None
    expected_colour_agreement: float | None = None
    evidence: float = 0.0
    rotation_std_deg: float | None = None
    location_fit: _LocationFit | None = None
    colour_leak: float | None = None

    def determined(self, limit_deg: float) -> bool:
        """Whether the fit's rotation is known within ``limit_deg`` (an
        unrefined fit is not judged: it has no uncertainty of its own)."""
        return self.rotation_std_deg is None or self.rotation_std_deg <= limit_deg

    @property
    def figure_ground_bonus(self) -> float:
        """What the figure-ground contrast adds to the fit's rank (see FIGURE_GROUND_WEIGHT)."""
        return FIGURE_GROUND_WEIGHT * min((self.figure_ground or 0.0) / FIGURE_GROUND_FULL, 1.0)

    @property
    def relative_colour(self) -> float:
        """The colour agreement as a share of what the part's own colours
        get in the scene (0 without a colour cue): about 1 on the part
        whether its colours are distinctive or common."""
        if self.colour_agreement is None or not self.expected_colour_agreement:
            return 0.0
        return self.colour_agreement / self.expected_colour_agreement

    @property
    def colour_rarity(self) -> float:
        """How rare the part's colours are in the scene (:func:`_rarity`;
        0 without a colour cue)."""
        if not self.expected_colour_agreement:
            return 0.0
        return _rarity(self.expected_colour_agreement)

    @property
    def colour_leak_penalty(self) -> float:
        """What the part's colour beyond the outline takes from the fit's
        colour rank among places (see COLOUR_LEAK_FLOOR; 0 without a
        colour cue)."""
        if self.colour_leak is None:
            return 0.0
        return (COLOUR_LEAK_WEIGHT * self.colour_rarity
                * max(self.colour_leak - COLOUR_LEAK_FLOOR, 0.0))

    @property
    def leaks_rare_colour(self) -> bool:
        """Whether the part's colours, rare in the scene, run on beyond the
        fit's outline too far for the fit to be on the part (see
        COLOUR_LEAK_MAX)."""
        return (self.colour_leak is not None and self.colour_leak >= COLOUR_LEAK_MAX
                and self.colour_rarity >= COLOUR_LEAK_MIN_RARITY)


@dataclass(frozen=True, slots=True, eq=False)
class _Located:
    """The training views that explain one image location best, before the final fit.

    Attributes
    ----------
    match : Match2D
        The alignment's match there (or one made of the best view).
    candidates : list of ViewCandidate
        The views that explain the image's edges there best, best first.
    colour_rivals : tuple of ViewCandidate
        At a place the part's colour proposed, the views that explain the
        outline of its colour there best and are not among ``candidates``
        (:func:`_colour_locations`); empty elsewhere.
    outline_only : bool
        Whether ``candidates`` explain the outline of the part's colour,
        the photo's edges there explaining no view
        (:data:`COLOUR_OUTLINE_MIN_RARITY`).
    """

    match: Match2D
    candidates: list[ViewCandidate]
    colour_rivals: tuple[ViewCandidate, ...] = ()
    outline_only: bool = False

    @property
    def evidence(self) -> float:
        """Log-likelihood ratio of the best view (ranks locations; candidates not empty)."""
        return self.candidates[0].log_likelihood_ratio


@dataclass(frozen=True, slots=True, eq=False)
class _LocationFit:
    """The refinement chosen at a location, before it is judged.

    Attributes
    ----------
    location : _Located
    result : RefinementResult
        The refinement (pose of the part's centred frame, object -> camera, mm).
    t_view : int
        The training view it started from.
    similarity : Similarity2D
        That view's frame -> image similarity, full-resolution pixels.
    start : Pose
        The pose they give (the refinement's start).
    fit_options : _FitOptions
        The location's refinements.
    """

    location: _Located
    result: RefinementResult
    t_view: int
    similarity: Similarity2D
    start: Pose
    fit_options: _FitOptions


def _view_candidate_count(surface: tuple[SurfaceSamples, NearSymmetries] | None) -> int:
    """Training views the view search returns per location for a part (its
    surface and near-symmetries, None without a mesh or refinement)."""
    if surface is not None and len(surface[1].transforms):
        return NEAR_SYMMETRIC_VIEW_CANDIDATES
    return VIEW_CANDIDATES


def _compares_sides(model: ObjectModel) -> bool:
    """Whether fits of the part compare its sides beyond the rival views'
    evidence (OTHER_SIDE_CANDIDATES): a part with colours of its own. Parts
    learned without colours get the same answers with and without (hard,
    novel, paper and hard-photos bench sets, learning seed 0: identical
    records) and would pay for the extra search and fits."""
    return model.colour_histogram is not None


def _fit_rank(result: RefinementResult) -> float:
    """Ranking key of a refinement: share of the contour that found its edge."""
    return float(result.inlier_fraction)


@dataclass(frozen=True, slots=True, eq=False)
class _Interior:
    """The scene's edges at the search level and the part's contour model,
    to count the edges inside a fit that it does not predict
    (:mod:`viewloc_core.interior_edges`).

    Attributes
    ----------
    edge_distance : (h, w) float32
        Distance of each level pixel to its nearest edge pixel.
    factor : float
        Level pixels per full-resolution pixel.
    contour : ContourModel
        The part's contour model (every kind of point predicts an edge).
    """

    edge_distance: NDArray[np.float32]
    factor: float
    contour: ContourModel

    def explained_share(self, camera: Camera, pose: Pose, samples: SurfaceSamples) -> float:
        """Share in [0, 1] of the edge pixels inside the part's silhouette at
        ``pose`` that its predicted contour explains (1 when it cannot be told).

        The silhouette is that of every surface sample, not only the visible
        ones: the facing test leaves different holes at rival poses, and an
        edge seen through such a hole would count against one pose alone.
        """
        projected = project_contour_view(camera, self.contour, pose)
        points_cam = samples.points_mm @ pose.R_m2c.T + pose.t_m2c
        if projected is None or float(points_cam[:, 2].min()) <= 0:
            return 1.0
        dot_px = camera.fx * samples.spacing_mm / float(pose.t_m2c[2])
        return interior_edges(self.edge_distance, self.factor, camera.project(points_cam),
                              dot_px, projected[0]).explained_share


@dataclass(frozen=True, slots=True, eq=False)
class _Shading:
    """The scene and the part's surface (:mod:`viewloc_core.shading`), and
    the part's colour in the scene when known."""

    image: NDArray[np.generic]
    samples: SurfaceSamples
    near: NearSymmetries
    colour: _ColourScene | None = None
    interior: _Interior | None = None

    @property
    def shading_weight(self) -> float:
        """Weight of the shading agreement in :meth:`rank`: PATTERNED_SHADING_WEIGHT
        for a part with a pattern of its own colours, SHADING_WEIGHT otherwise."""
        return SHADING_WEIGHT if self.samples.albedo is None else PATTERNED_SHADING_WEIGHT

    def rank(self, camera: Camera, result: RefinementResult,
             at_least: float = -math.inf) -> float:
        """Ranking key of fits of different views at one location: the share
        of the contour confirmed, plus the shading agreement weighted by
        :attr:`shading_weight` (0 when the part shows too little of itself)
        and the colour agreement weighted by :data:`COLOUR_WEIGHT` (a view
        fitted beside the part covers less of its colours), less the share
        of the edges inside it that its contour leaves unexplained, weighted
        by :data:`INTERIOR_EDGE_WEIGHT` (when :attr:`interior` is given).

        A fit whose key is certainly below ``at_least`` gets -inf instead,
        without the cues that cannot lift it that far: each cue lies in
        [0, 1], so the contour share bounds the key before any is read, and
        the key without the interior edges (which only lower it) bounds it
        before they are counted. Most rival fits are out of the running
        early (hard bench set: 14.5 of the 28 rankings an image, 11 of
        them before any cue is read; novel: 13 of 26; LM-O, ape and cat,
        with a shading weight of 0.1: 35 of 49, 27 of them after the colour
        alone).
        """
        inliers = _fit_rank(result)
        shading_weight = self.shading_weight
        if inliers + shading_weight + (0.0 if self.colour is None else COLOUR_WEIGHT) \
                + _RANK_BOUND_SLACK < at_least:
            return -math.inf
        # Both cues read the same visible samples: projected once.
        visible = visible_samples(self.samples, camera, result.pose)
        colour_term = 0.0
        if self.colour is not None:
            # The cheaper cue first: it may settle the bound on its own.
            colour_term = COLOUR_WEIGHT * (self.colour.agreement(
                camera, result.pose, self.samples, visible.uv) or 0.0)
            if inliers + shading_weight + colour_term + _RANK_BOUND_SLACK < at_least:
                return -math.inf
        agreement = shading_agreement(self.image, camera, result.pose, self.samples, visible)
        rank = inliers + shading_weight * (agreement or 0.0)
        if rank + colour_term + _RANK_BOUND_SLACK < at_least:
            return -math.inf
        if self.interior is not None:
            rank -= INTERIOR_EDGE_WEIGHT * (
                1.0 - self.interior.explained_share(camera, result.pose, self.samples))
        return rank + colour_term


#: Margin of the bounds in :meth:`_Shading.rank` over rounding (the cues are
#: sums and means of floats in [0, 1]): a fit is cut short only when its
#: bound is clearly below the key it must reach.
_RANK_BOUND_SLACK = 1e-9


def _train_diameter_px(model: ObjectModel) -> float:
    """The part's diameter in the training views, pixels (image scale 1)."""
    return model.f_train_px * model.diameter_mm / model.d0_mm


@dataclass(frozen=True, slots=True, eq=False)
class _ColourScene:
    """The part's colour in the scene (:mod:`viewloc_core.part_colour`), on
    the pyramid level searched.

    Attributes
    ----------
    log_ratio : (h, w) float32
        Per-pixel log likelihood ratio part vs. scene of the level's colours.
    posterior : (h, w) float32
        P(part | colour) of each pixel of the level.
    factor : float
        Level pixels per full-resolution pixel.
    expected_agreement : float
        The agreement the part's own colours get in this scene
        (:func:`part_colour.expected_agreement`), in (0, 1).
    bin_posterior : (N_BINS,) float32
        P(part | colour) of each colour bin in this scene, to read the
        posterior of the full-resolution image (:meth:`full_posterior`).
    """

    log_ratio: NDArray[np.float32]
    posterior: NDArray[np.float32]
    factor: float
    expected_agreement: float
    bin_posterior: NDArray[np.float32]

    @classmethod
    def of(cls, model: ObjectModel, level: NDArray[np.generic],
           factor: float) -> _ColourScene | None:
        """The colour cue, or None when the model knows no colours of its
        part or the scene is grey."""
        if model.colour_histogram is None:
            return None
        binned = part_colour.bin_log_ratios(level, model.colour_histogram)
        if binned is None:
            return None
        bins, bin_ratio = binned
        log_ratio = bin_ratio[bins]
        return cls(log_ratio, part_colour.posterior(log_ratio), factor,
                   part_colour.expected_agreement(model.colour_histogram, bin_ratio),
                   part_colour.posterior(bin_ratio))

    def full_posterior(self, image: NDArray[np.generic]) -> NDArray[np.float32]:
        """P(part | colour) of each pixel of the full-resolution ``image``
        (the scene's colour statistics as the level gave them), (H, W); the
        level's :attr:`posterior` when the image has no colours to read."""
        full = part_colour.posterior_map(image, self.bin_posterior)
        return self.posterior if full is None else full

    def seeds(self, model: ObjectModel, config: AlignConfig,
              within: NDArray[np.float64] | None = None) -> list[NDArray[np.float64]]:
        """Training-view frame -> level similarities to search at each
        location the colour proposes, (K, 4) per location, best first;
        with ``within`` (level pixels ``x0, y0, x1, y1``) only locations
        centred in it."""
        train_diameter_px = _train_diameter_px(model)
        halves = COLOUR_WINDOW_SHARE * train_diameter_px * np.geomspace(
            config.min_scale, config.max_scale, COLOUR_WINDOW_SIZES)
        out = []
        for prop in part_colour.propose(self.log_ratio, halves, COLOUR_LOCATIONS, within,
                                        COLOUR_PROPOSAL_EXCLUSION):
            scale = prop.half_size_px / (COLOUR_WINDOW_SHARE * train_diameter_px)
            x, y = part_colour.centroid(self.log_ratio, prop.x, prop.y,
                                        0.5 * prop.half_size_px / COLOUR_WINDOW_SHARE)
            out.append(np.array([[x, y, np.radians(a), scale * f]
                                 for f in COLOUR_SEED_SCALES
                                 for a in COLOUR_SEED_ANGLES_DEG], np.float64))
        return out

    def outline_features(self) -> tuple[ImageFeatures, ChanceRates]:
        """The edges of the part's colour on the level (:attr:`posterior`
        as an image: the outline of what has the part's colours), and their
        chance rates, for the view search."""
        feats = extract_features((self.posterior * 255.0).astype(np.uint8), edges_only=True)
        return feats, chance_rates(feats)

    def agreement(self, camera: Camera, pose: Pose, samples: SurfaceSamples,
                  visible_uv: NDArray[np.float64] | None = None) -> float | None:
        """Mean P(part | colour) under the surface samples the camera sees at
        ``pose`` (the part's centred frame); None when none is seen.
        ``visible_uv``: their image positions when the caller has them
        already (:func:`viewloc_core.shading.visible_samples`)."""
        uv = visible_samples(samples, camera, pose)[0] if visible_uv is None else visible_uv
        if not len(uv):
            return None
        return part_colour.agreement(self.posterior, (uv + 0.5) * self.factor - 0.5)

    def leak(self, camera: Camera, pose: Pose, samples: SurfaceSamples) -> float | None:
        """How much of the part's colour lies just outside its outline at
        ``pose`` (the part's centred frame): the mean P(part | colour) in
        the ring of :func:`viewloc_core.figure_ground.ring_values` on the
        level, over :attr:`expected_agreement`; None when too little of
        the ring is in the image."""
        ring = ring_values(camera.scaled(self.factor), pose, samples, self.posterior)
        if ring is None or len(ring) < MIN_RING_PIXELS:
            return None
        return float(np.asarray(ring, np.float64).mean()) / self.expected_agreement


def _colour_locations(
    model: ObjectModel, colour: _ColourScene, feats: ImageFeatures, templates: ViewTemplates,
    chance: ChanceRates, config: AlignConfig, taken: list[_Located],
    within: NDArray[np.float64] | None = None, other_side: int = 0,
) -> list[_Located]:
    """The view search at the locations the part's colour proposes, as
    locations of their own (an alignment match made of the best view).

    A proposal whose best view lands within a quarter of the part's image
    diameter of a location in ``taken`` (or of an earlier proposal's) adds
    nothing and is dropped. ``within``: see :meth:`_ColourScene.seeds`;
    ``other_side``: see :func:`search_views`.

    Each location also gets the views that explain the outline of the
    part's colour there best (the view search on
    :meth:`_ColourScene.outline_features`, from the same seeds), up to
    :data:`COLOUR_OUTLINE_CANDIDATES`, as rivals of its fit
    (:attr:`_Located.colour_rivals`, :func:`_final_detection`). Where the
    photo's edges explain no view (:data:`COLOUR_MIN_EVIDENCE`) and the
    part's colours are rare in the scene (:data:`COLOUR_OUTLINE_MIN_RARITY`),
    the location's views are those of the outline alone.
    """
    tr = model.training
    out: list[_Located] = []
    outline: tuple[ImageFeatures, ChanceRates] | None = None

    def outline_features() -> tuple[ImageFeatures, ChanceRates]:
        # Made once per image, and only when a location needs it.
        nonlocal outline
        if outline is None:
            outline = colour.outline_features()
        return outline

    rare = _rarity(colour.expected_agreement) >= COLOUR_OUTLINE_MIN_RARITY
    for seeds in colour.seeds(model, config, within):
        offsets = _colour_offsets(COLOUR_OFFSET_SHARE * float(np.median(seeds[:, 3]))
                                  * _train_diameter_px(model))
        candidates = search_views(feats, templates, seeds, chance, VIEW_CANDIDATES,
                                  offsets, COLOUR_KEPT_SEEDS, COLOUR_SCREEN_ANGLES_DEG,
                                  other_side)
        on_edges = bool(candidates) and candidates[0].log_likelihood_ratio > COLOUR_MIN_EVIDENCE
        if not on_edges:
            if not rare:
                continue
            outline_feats, outline_chance = outline_features()
            candidates = search_views(outline_feats, templates, seeds, outline_chance,
                                      VIEW_CANDIDATES, offsets, COLOUR_KEPT_SEEDS,
                                      COLOUR_SCREEN_ANGLES_DEG, other_side)
            if not candidates or candidates[0].log_likelihood_ratio <= COLOUR_MIN_EVIDENCE:
                continue
        best = candidates[0]
        reach = 0.25 * best.sim[3] * _train_diameter_px(model)
        if any(np.hypot(*(best.sim[:2] - loc.candidates[0].sim[:2])) < reach
               for loc in taken + out):
            continue
        model_view = int(tr.model_view[best.view])
        sim_mv = sim2.compose(best.sim, sim2.inverse(tr.sim_to_model[best.view]))
        g, n_pairs = log_probability(model.model_views[model_view], feats, sim_mv)
        match = Match2D(model_view, sim_mv, g, best.hit_fraction, n_pairs,
                        best.log_likelihood_ratio)
        rivals: tuple[ViewCandidate, ...] = ()
        if on_edges:
            known = {c.view for c in candidates}
            outline_feats, outline_chance = outline_features()
            rivals = tuple(c for c in search_views(outline_feats, templates, seeds,
                                                   outline_chance, COLOUR_OUTLINE_CANDIDATES,
                                                   offsets, COLOUR_KEPT_SEEDS,
                                                   COLOUR_SCREEN_ANGLES_DEG)
                           if c.view not in known)
        out.append(_Located(match, candidates, rivals, outline_only=not on_edges))
    return out


def _other_sides(
    model: ObjectModel, loc: _Located, factor: float, camera: Camera, edges: EdgePyramid,
    contour: ContourModel, shading: _Shading, t_view: int, similarity: Similarity2D,
    start: Pose, result: RefinementResult, fit_options: _FitOptions,
    rivals: list[ViewCandidate] | None = None,
) -> tuple[RefinementResult, int, Similarity2D, Pose]:
    """The fit of another of the location's candidate views, when its contour
    and shading together agree better with the image than ``result``'s.

    An outline can fit equally well from views far apart: a smooth part's
    front and back, or any two views whose outlines are alike (hard bench
    set, free-form part: whole outlines confirmed at poses 90-180° wrong).
    The starts are the candidates with at least ``OTHER_VIEW_EVIDENCE_SHARE``
    of the best one's evidence and those that see the part from the other
    side than the fit's view whatever theirs (OTHER_SIDE_CANDIDATES), then
    the fit turned by each of the part's
    near-symmetries (:mod:`viewloc_core.near_symmetry`: the half turns that
    leave a nearly ellipsoidal part's outline almost as it was; hard bench
    set, free-form part: 6 of 16 wrong poses lay within 30° of one), and
    the fit mirrored in each near mirror plane and reversed in depth
    (:meth:`NearSymmetries.reversals`: the same outline tilted the other
    way; hard bench set, free-form part: 7 of 15 wrong poses lay within 25°
    of it), and, on every part, the fit turned over about its outline's
    axes in the image (:meth:`NearSymmetries.outline_turns`). See
    :func:`_best_rival` for how they compete.

    When a rival wins, its own twins, reversals and outline turns are tried
    in a further round, up to ``OTHER_SIDE_ROUNDS`` in all: the first fit's
    are made from a pose that may be far from the truth, and the winner's
    may lie near it (hard bench set, free-form part: two images in which
    the truth lay near a reversal of the winning rival, never tried). When
    none wins, the further round tries those of the best full fit that lost
    by less than ``NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP`` instead: a part turned
    over ranks within hundredths of its truth, and the truth may lie near a
    turn of the runner-up rather than of the first fit (hard bench set,
    learning seed 1, free-form part: a first fit 52° off, its runner-up
    turned over, the truth a half turn of that runner-up).

    With ``rivals``, those views are the rival starts instead of the
    location's candidates, whatever their evidence, and the first round
    leaves out the fit's own twins, reversals and outline turns: ``result``
    already won against them (:func:`_wider_look`).
    """
    chosen = (result, t_view, similarity, start)
    tried = [result.pose.R_m2c]
    if rivals is None:
        # The candidates with enough evidence, and those of the other side
        # whatever theirs (OTHER_SIDE_CANDIDATES).
        directions = view_templates(model).directions
        other_side_cos = math.cos(math.radians(OTHER_SIDE_MIN_DEG))
        sides = _compares_sides(model)
        candidates = [c for c in loc.candidates[1:]
                      if c.log_likelihood_ratio >= OTHER_VIEW_EVIDENCE_SHARE * loc.evidence
                      or (sides and float(directions[c.view] @ directions[t_view])
                          <= other_side_cos)]
    else:
        candidates = rivals
    # The fit whose twins, reversals and outline turns the round tries
    # (None: the chosen).
    turned: RefinementResult | None = None
    turns = rivals is None
    for _ in range(OTHER_SIDE_ROUNDS):
        winner, runner_up = _best_rival(model, candidates, factor, camera, edges, contour,
                                        shading, *chosen, tried, fit_options, turned, turns)
        turns = True
        candidates = []  # the location's views were all tried in the first round
        if winner[0] is not chosen[0]:
            chosen, turned = winner, None
            tried.append(winner[0].pose.R_m2c)
        elif runner_up is not None and turned is None:
            turned = runner_up
        else:
            break
    return chosen


def _best_rival(
    model: ObjectModel, candidates: list[ViewCandidate], factor: float,
    camera: Camera, edges: EdgePyramid, contour: ContourModel, shading: _Shading,
    result: RefinementResult, t_view: int, similarity: Similarity2D, start: Pose,
    tried: list[NDArray[np.float64]], fit_options: _FitOptions,
    turned: RefinementResult | None = None, turns: bool = True,
) -> tuple[tuple[RefinementResult, int, Similarity2D, Pose], RefinementResult | None]:
    """One round of :func:`_other_sides`: the fit of the rival start that
    ranks highest, or ``result`` (the same object) when none ranks higher;
    and, when none does on a part with near-symmetries, the full fit that
    ranked highest below it but not more than
    ``NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP`` below (None otherwise).

    The rival starts are ``candidates`` (view search runners-up), each
    also nearer and farther (``RIVAL_SCALE_FACTORS``), and the twins,
    reversals and outline turns of ``turned`` (``result`` when None;
    none when not ``turns``). Each
    start at least
    ``DISTINCT_VIEW_DEG`` from the rotations in ``tried`` (extended in
    place) gets a short coarse fit; the best by :meth:`_Shading.rank` gets
    the full fit when it ranks higher than ``result`` (on a part with
    near-symmetries, the best ``NEAR_SYMMETRIC_FULL_FITS`` unless
    ``NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP`` below ``result``), and the
    full fit that ranks highest wins when it ranks higher than ``result``.
    """
    sym = model.symmetry_group()
    starts = []
    for cand in candidates:
        sim_c = _to_full_resolution(cand.sim, factor)
        starts.append((cand.view, sim_c, _pose_centred(model, cand.view, sim_c, camera),
                       fit_options.quick))
    view_starts = len(starts)
    # The fit turned by each near-symmetry, mirrored and reversed in depth,
    # or turned over about its outline's axes keeps the 2D match's view and
    # similarity: no training view shows it. The outline turns are tried
    # on every part, not only near-symmetric ones: an outline nearly
    # symmetric about an axis in the image (a tee from the front, a bracket
    # from its side) fits as well turned over, whatever the part's own
    # symmetries (novel and hard bench sets, learning seeds 0-4: 4 images
    # right in 6D that were not, none lost; about 3.5 more short fits an
    # image).
    base = (result if turned is None else turned).pose
    if turns:
        starts += [(t_view, similarity, twin, fit_options.twin)
                   for twin in shading.near.twins(base) + shading.near.reversals(base)
                   + shading.near.outline_turns(base)]
    distinct = []
    for i, (view_c, sim_c, pose_c, quick_options) in enumerate(starts):
        if any_within_angle_deg(pose_c.R_m2c, tried, sym, DISTINCT_VIEW_DEG):
            continue
        tried.append(pose_c.R_m2c)
        distinct.append((view_c, sim_c, pose_c, quick_options))
        if i < view_starts:
            # A rival view nearer and farther too (RIVAL_SCALE_FACTORS):
            # the same image position and turn, another depth.
            for scale_factor in RIVAL_SCALE_FACTORS:
                sim_f = replace(sim_c, scale=sim_c.scale * scale_factor)
                distinct.append((view_c, sim_f, _pose_centred(model, view_c, sim_f, camera),
                                 quick_options))

    chosen = (result, t_view, similarity, start)
    if not distinct:
        return chosen, None
    first_rank = shading.rank(camera, result)
    near_symmetric = len(shading.near.transforms) > 0
    # The least rank a quick fit needs to become a contender (below): the
    # ranking of one that cannot reach it stops early.
    contender_floor = (first_rank - NEAR_SYMMETRIC_MAX_SHORT_FIT_GAP if near_symmetric
                       else first_rank)

    def quick_fit(start_c: tuple[int, Similarity2D, Pose, RefineOptions],
                  ) -> tuple[float, int, Similarity2D, Pose, Pose]:
        view_c, sim_c, pose_c, quick_options = start_c
        quick = refine_pose(edges, camera, pose_c, contour, quick_options)
        return (shading.rank(camera, quick, at_least=contender_floor), view_c, sim_c, pose_c,
                quick.pose)

    # The starts' fits are independent and compiled: they share the two
    # cores (a single location's rivals are most of a localization's pose
    # stage, and would otherwise leave the other core idle).
    quick_fits = each_on_both(quick_fit, distinct)
    quick_fits.sort(key=lambda f: -f[0])
    # A quick fit runs a few iterations on half the points, so its rank is
    # not quite on the full fit's scale: it can fall short of the fit it
    # competes with even where its full fit would rank higher. On a
    # near-symmetric part, whose rival fits rank within hundredths of each
    # other, the best few starts always get
    # their full fits (hard bench set, free-form part, models learned with
    # seeds 0/1/2, the best one: 6D right in 23/20/19 -> 24/22/19 of 40
    # images); on other parts the best one does when it ranks higher.
    if near_symmetric:
        contenders = [f for f in quick_fits[:NEAR_SYMMETRIC_FULL_FITS]
                      if f[0] >= contender_floor]
    else:
        contenders = [f for f in quick_fits[:1] if f[0] > contender_floor]

    def full_fit(quick_pose: Pose) -> tuple[RefinementResult, float]:
        other = refine_pose(edges, camera, quick_pose, contour, fit_options.final)
        # Only a full fit that ranks higher than ``result`` matters, or
        # (as the runner-up) one at least at the contender floor.
        return other, shading.rank(camera, other, at_least=contender_floor)

    full_fits = each_on_both(full_fit, [f[4] for f in contenders])
    current = first_rank
    runner_up, runner_up_rank = None, -math.inf
    for (_, view_c, sim_c, pose_c, _), (other, rank) in zip(contenders, full_fits, strict=True):
        if rank > current:
            current, chosen = rank, (other, view_c, sim_c, pose_c)
        elif near_symmetric and rank >= contender_floor and rank > runner_up_rank:
            runner_up, runner_up_rank = other, rank
    return chosen, (runner_up if chosen[0] is result else None)


def _wider_look(
    model: ObjectModel, feats: ImageFeatures, chance: ChanceRates, factor: float,
    camera: Camera, edges: EdgePyramid, contour: ContourModel, shading: _Shading,
    fitted: _Fitted,
) -> _Fitted:
    """A detection's location searched again for more views, whose fits
    compete with the detection's as its own rival views did
    (:func:`_other_sides`); the detection judged again when one wins.

    The view search ranks a real photo's views by their outline's edges,
    which clutter and the part's own shading confuse: at the right place,
    the views near the truth often rank beyond the candidates fitted (LM-O
    ape, turned fits at the right place: 35th-73rd of 162 in the screen),
    while the truth's fit outranks the chosen one by the contour, shading
    and colour together (:meth:`_Shading.rank`). The location's best
    candidates are the seeds of a search that screens
    :data:`WIDER_SCREENED_VIEWS` views and returns
    :data:`WIDER_VIEW_CANDIDATES`; those the location did not have are the
    rivals.
    """
    fit = fitted.location_fit
    if fit is None:
        return fitted
    loc = fit.location
    seeds = np.array([c.sim for c in loc.candidates[:WIDER_LOOK_SEEDS]])
    known = {c.view for c in loc.candidates}
    rivals = [c for c in search_views(feats, view_templates(model), seeds, chance,
                                      WIDER_VIEW_CANDIDATES,
                                      screened_views=WIDER_SCREENED_VIEWS)
              if c.view not in known]
    if not rivals:
        return fitted
    result, t_view, similarity, start = _other_sides(
        model, loc, factor, camera, edges, contour, shading, fit.t_view, fit.similarity,
        fit.start, fit.result, fit.fit_options, rivals)
    if result is fit.result:
        return fitted
    return _judged(model, camera, contour, shading,
                   _LocationFit(loc, result, t_view, similarity, start, fit.fit_options))


def _refit_from_other_starts(
    model: ObjectModel, loc: _Located, factor: float, camera: Camera, edges: EdgePyramid,
    contour: ContourModel, t_view: int, similarity: Similarity2D, start: Pose,
    result: RefinementResult, fit_options: _FitOptions,
) -> tuple[RefinementResult, int, Similarity2D, Pose]:
    """A poor first refinement tried again from other starts; the better fit
    and its start (training view, similarity and the pose they give).

    The refinement's capture range in depth is a few %, less than the error
    of a depth from the 2D scale: other depths, then the runners-up of the
    view search, are the other starts. Each gets a short coarse fit; the best
    one the full fit, which replaces ``result`` when it confirms more contour.
    """
    starts = [(t_view, Similarity2D(similarity.x, similarity.y, similarity.angle_deg,
                                    similarity.scale * f)) for f in DEPTH_STARTS]
    starts += [(c.view, _to_full_resolution(c.sim, factor))
               for c in loc.candidates[1:1 + RUNNER_UP_STARTS]]

    def quick_fit(start_c: tuple[int, Similarity2D]) -> tuple[float, int, Similarity2D, Pose, Pose]:
        t_c, sim_c = start_c
        pose_c = _pose_centred(model, t_c, sim_c, camera)
        quick = refine_pose(edges, camera, pose_c, contour, fit_options.quick)
        return _fit_rank(quick), t_c, sim_c, pose_c, quick.pose

    # Two starts at a time, one per core, taken in order until one fits
    # well (when the first of a pair does, the second was fitted in vain,
    # meanwhile on the other core).
    best_start: tuple[float, int, Similarity2D, Pose, Pose] | None = None
    fits_well = False
    for first in range(0, len(starts), 2):
        for fit in each_on_both(quick_fit, starts[first:first + 2]):
            if best_start is None or fit[0] > best_start[0]:
                best_start = fit
            fits_well = fit[0] >= GOOD_FIT_FRACTION
            if fits_well:
                break
        if fits_well:
            break
    if best_start is not None:
        other = refine_pose(edges, camera, best_start[4], contour, fit_options.final)
        if _fit_rank(other) > _fit_rank(result):
            return other, best_start[1], best_start[2], best_start[3]
    return result, t_view, similarity, start


def _tilted_refit(edges: EdgePyramid, camera: Camera, contour: ContourModel, sym: Symmetries,
                  result: RefinementResult, fit_options: _FitOptions) -> RefinementResult:
    """A full fit, or the fit from its pose tilted out of the image plane
    when that confirms clearly more of the contour.

    A fit that starts more than about 10° off in rotation often stops at a
    pose that explains part of the outline (TILT_DEG): a wrong tilt moves
    a smooth outline little. Quick fits from the pose tilted by
    ``TILT_DEG`` about six axes in the image plane (:data:`_TILTS`), about
    the part's centre, reach the neighbouring basins; the one that
    confirms the most of its contour gets the full fit when it ends
    elsewhere, and that fit replaces ``result`` under the bars of
    TILT_MIN_MOVE_DEG and TILT_MIN_GAIN. From the truth turned 5 / 10 /
    15 / 20° (the figures of TILT_DEG) the fits ended within 3° in 0.94 /
    0.87 / 0.71 / 0.61 of the cases instead of 0.90 / 0.68 / 0.43 / 0.31.

    Parameters
    ----------
    edges : EdgePyramid
    camera : Camera
    contour : ContourModel
    sym : Symmetries
        The part's symmetries: a turn about them is no move.
    result : RefinementResult
        The full fit (pose of the part's centred frame, object -> camera, mm).
    fit_options : _FitOptions
        The location's quick and full refinements.

    Returns
    -------
    RefinementResult
        ``result`` or the full fit of the best tilted restart.
    """
    R = result.pose.R_m2c
    starts = [Pose(tilt @ R, result.pose.t_m2c) for tilt in _TILTS]
    quick_fits = each_on_both(
        lambda start: refine_pose(edges, camera, start, contour, fit_options.quick), starts)
    best = max(quick_fits, key=_fit_rank)
    if (_fit_rank(best) <= _fit_rank(result)
            or within_angle_deg(best.pose.R_m2c, R, sym, TILT_MIN_MOVE_DEG)):
        return result
    other = refine_pose(edges, camera, best.pose, contour, fit_options.final)
    if (_fit_rank(other) >= _fit_rank(result) + TILT_MIN_GAIN
            and not within_angle_deg(other.pose.R_m2c, R, sym, TILT_MIN_MOVE_DEG)):
        return other
    return result


def _final_detection(
    model: ObjectModel, loc: _Located, level: NDArray[np.generic], factor: float,
    camera: Camera, edges: EdgePyramid | None, contour: ContourModel | None,
    view_radius_px: float, shading: _Shading | None = None,
) -> _Fitted:
    """6D pose of the best view at a location and, with a contour model, its
    refinement; with a colour cue and the part's surface, how well the
    part's colours explain the pose's visible surface."""
    best = loc.candidates[0]
    if contour is None or edges is None:
        # Without refinement the 2D fit decides the pose: refit at training scale.
        sim_level, score = _refit_at_model_scale(model, best.view, best.sim, level,
                                                 view_radius_px)
        similarity = _to_full_resolution(sim_level, factor)
        return _described(model, camera, shading, loc, score, best.view, similarity,
                          _pose_centred(model, best.view, similarity, camera))
    t_view = best.view
    similarity = _to_full_resolution(best.sim, factor)
    pose_centred = _pose_centred(model, t_view, similarity, camera)
    fit_options = _FitOptions.near(edges, camera, pose_centred, model.diameter_mm)
    result = refine_pose(edges, camera, pose_centred, contour, fit_options.final)
    result = _tilted_refit(edges, camera, contour, model.symmetry_group(), result,
                           fit_options)
    if _fit_rank(result) < GOOD_FIT_FRACTION:
        result, t_view, similarity, pose_centred = _refit_from_other_starts(
            model, loc, factor, camera, edges, contour, t_view, similarity, pose_centred,
            result, fit_options)
    if shading is not None and (len(loc.candidates) > 1 or len(shading.near.transforms)):
        result, t_view, similarity, pose_centred = _other_sides(
            model, loc, factor, camera, edges, contour, shading, t_view, similarity,
            pose_centred, result, fit_options)
    if shading is not None and loc.colour_rivals:
        # The views of the colour's outline compete as the wider look's do
        # (_wider_look): without the fit's own twins and turns in their
        # first round, which either were tried above or, at a location of
        # one view and a part without near-symmetries, never are.
        result, t_view, similarity, pose_centred = _other_sides(
            model, loc, factor, camera, edges, contour, shading, t_view, similarity,
            pose_centred, result, fit_options, list(loc.colour_rivals))
    return _judged(model, camera, contour, shading,
                   _LocationFit(loc, result, t_view, similarity, pose_centred, fit_options))


def _judged(model: ObjectModel, camera: Camera, contour: ContourModel,
            shading: _Shading | None, fit: _LocationFit) -> _Fitted:
    """The detection of a location's refinement: at the refined pose when
    the refinement holds, else at its start with the lower of the
    location's 2D fit (its best view's hit fraction) and the refinement's
    inlier fraction as its score."""
    result, pose_centred = fit.result, fit.start
    # The depth from the 2D scale is uncertain by several %, the image
    # position much less: a refinement that wanders sideways in the
    # image has left the object (a wrong 2D match cannot be rescued
    # here). Sideways is measured in pixels: in millimetres a depth
    # correction of an object off the optical axis moves it sideways too
    # (hard bench set: 10% of depth at 270 mm off axis is 27 mm).
    z = float(pose_centred.t_m2c[2])
    start_px, end_px = camera.project(np.stack([pose_centred.t_m2c, result.pose.t_m2c]))
    diameter_px = camera.fx * model.diameter_mm / z
    fits = result.converged or result.mean_residual_px < 1.0
    refined = False
    pose_std = None
    chance_corrected = None
    rotation_std = None
    if (fits and result.inlier_fraction >= 0.6
            and float(np.hypot(*(end_px - start_px))) < 0.25 * diameter_px
            and abs(float(result.pose.t_m2c[2]) - z) < 0.25 * z):
        pose_centred = result.pose
        refined = True
        pose_std = result.pose_std
        score = float(result.inlier_fraction)
        chance_corrected = result.score
        rotation_std = rotation_std_deg(result.covariance_6x6, result.pose,
                                        model.symmetry_group())
    else:
        score = min(fit.location.candidates[0].hit_fraction, float(result.inlier_fraction))
    # The contour outside the image counts as unconfirmed, as the 2D
    # fit's samples outside do (align.coverage): a fit that puts most of
    # the part beyond the border is judged by the little left inside.
    # Bench, learning seed 0: part-free images with a detection paper
    # 3 -> 2 of 10, hard 7 -> 6 of 12, novel 11 -> 9 of 12, LM-O 9 -> 7
    # of 18; LM-O's wrong-place answers 350 -> 260 of 745 targets, right
    # ones 182 -> 183; AR the same but novel's (0.869 -> 0.877 AR_MSSD).
    score *= contour_in_image_fraction(camera, contour, pose_centred,
                                       fit.fit_options.final.self_edge_weight)
    return _described(model, camera, shading, fit.location, score, fit.t_view, fit.similarity,
                      pose_centred, refined, pose_std, chance_corrected, rotation_std, fit)


def _described(
    model: ObjectModel, camera: Camera, shading: _Shading | None, loc: _Located, score: float,
    t_view: int, similarity: Similarity2D, pose_centred: Pose, refined: bool = False,
    pose_std: NDArray[np.float64] | None = None, chance_corrected: float | None = None,
    rotation_std: float | None = None, fit: _LocationFit | None = None,
) -> _Fitted:
    """The detection at ``pose_centred`` (the part's centred frame) and the
    cues that rank it: with the part's surface, its colour agreement and
    figure-ground contrast. See :class:`_Fitted` for the rest."""
    colour_agreement = None
    expected_colour_agreement = None
    colour_leak = None
    figure_ground = None
    if shading is not None:
        visible_uv = None
        if shading.colour is not None:
            # The colour agreement and the contrast read the same visible
            # samples: projected once.
            visible_uv = visible_samples(shading.samples, camera, pose_centred)[0]
            colour_agreement = shading.colour.agreement(camera, pose_centred, shading.samples,
                                                        visible_uv)
            expected_colour_agreement = shading.colour.expected_agreement
            colour_leak = shading.colour.leak(camera, pose_centred, shading.samples)
        figure_ground = figure_ground_contrast(shading.image, camera, pose_centred,
                                               shading.samples, visible_uv)
    # The model was learned with the bounding-box centre as origin.
    pose = Pose(pose_centred.R_m2c,
                pose_centred.t_m2c - pose_centred.R_m2c @ model.origin_offset_mm)
    # The reported reference point is where the pose puts the object's own
    # origin (the similarity's centre is the bounding-box centre's image).
    ref_xy = camera.project(pose.t_m2c[None])[0]
    similarity = Similarity2D(float(ref_xy[0]), float(ref_xy[1]), similarity.angle_deg,
                              similarity.scale)
    if len(model.symmetries) > 1 or model.symmetry_axis is not None:
        # Symmetric equivalents look the same: report the one whose axes are
        # closest to the camera's, so the answer does not jump between them.
        pose = canonical_pose(pose, model.symmetry_group())
    return _Fitted(Detection(
        score=float(score),
        log_probability=float(loc.match.log_probability),
        model_view=int(model.training.model_view[t_view]),
        azimuth_deg=float(model.training.azimuth_deg[t_view]),
        polar_deg=float(model.training.polar_deg[t_view]),
        similarity=similarity,
        pose=pose,
        refined=refined,
        pose_std=pose_std,
    ), chance_corrected, colour_agreement, figure_ground, expected_colour_agreement,
        loc.evidence, rotation_std, fit, colour_leak)


def _confirmed(det: Detection) -> bool:
    """Whether a refinement confirmed the detection's contour (see GOOD_FIT_FRACTION)."""
    return det.refined and det.score >= GOOD_FIT_FRACTION


def _settled(fit: _Fitted) -> bool:
    """Whether a first fit needs no spare location beside it: its contour is
    confirmed, beyond chance as well (both at GOOD_FIT_FRACTION), and its
    inside does not look like its surroundings (see
    FIRST_FIT_MIN_FIGURE_GROUND; no colour, no doubt).

    On texture the plain fraction is high wherever edges of any orientation
    are: a wrong fit on wood confirmed 0.88 of its contour, 0.83 beyond
    chance, while the part lay at the fourth location (hard bench set).
    Replayed on every located place's fit (hard set, learning seeds 0-4,
    three spares): right detections 364 -> 367 of 400, fits per image 1.96
    -> 2.08.
    """
    return (_confirmed(fit.detection)
            and (fit.chance_corrected or 0.0) >= GOOD_FIT_FRACTION
            and (fit.figure_ground is None
                 or fit.figure_ground >= FIRST_FIT_MIN_FIGURE_GROUND))


def _resolved(fit: _Fitted) -> bool:
    """Whether a level's best fit makes a search of the finer level
    needless (:func:`localize_in_scene`): it settled, or it confirms
    :data:`FINER_SEARCH_NEEDLESS_FRACTION` of its contour, beyond chance
    as well, whatever its figure-ground contrast."""
    return _settled(fit) or (fit.detection.refined
                             and fit.detection.score >= FINER_SEARCH_NEEDLESS_FRACTION
                             and (fit.chance_corrected or 0.0)
                             >= FINER_SEARCH_NEEDLESS_FRACTION)


def _convincing(fit: _Fitted, in_colour: bool = False, bar_share: float = 1.0) -> bool:
    """Whether a spare location's fit may compete (see SPARE_MIN_CHANCE_CORRECTED
    and, in a colour scene, SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR), the bar
    times ``bar_share`` (:func:`_spare_bar_share`)."""
    bar = SPARE_MIN_CHANCE_CORRECTED_IN_COLOUR if in_colour else SPARE_MIN_CHANCE_CORRECTED
    return fit.chance_corrected is not None and fit.chance_corrected >= bar * bar_share


def _after_the_first_convincing(ranked: list[Detection], fits: list[_Fitted],
                                in_colour: bool, bar_share: float) -> list[Detection]:
    """The first of the ranked detections, and those after it whose fits
    are convincing (:func:`_convincing`, the bar times ``bar_share``).

    A second detection is a further place where the part is claimed to
    be, as a spare location's fit is a further place where it may be: it
    is held to the spares' bar. The first fits of a request for several
    parts are not spares, but those after the best come from places the
    view search ranked lower, and a wrong one took the place of a copy
    that the locations after it held (multi bench set: see
    ALIGNED_LOCATIONS_PER_DETECTION; over four runs detections elsewhere
    51 -> 43 and copies found 325 -> 327 of 384).
    ``fits`` holds the fits of the detections; an unrefined one is not
    convincing. Only a request for several detections needs this: one
    wanted is the first ranked.
    """
    if len(ranked) < 2:
        return ranked
    by_detection = {id(f.detection): f for f in fits}
    return ranked[:1] + [d for d in ranked[1:]
                         if _convincing(by_detection[id(d)], in_colour, bar_share)]


def _spare_bar_share(min_score: float, default_min_score: float) -> float:
    """What share of the spares' bar (:func:`_convincing`) a request's
    ``min_score`` leaves: the share it leaves of the model's default, at
    most all of it.

    A request that accepts fits confirming less of the contour than the
    default (a part partly hidden confirms at most the share it shows)
    must accept such a fit at a spare location too: with the bar fixed, a
    half-hidden part was reported when the view search ranked its place
    first and never when it ranked it second (paper bench set, a barbell
    two-thirds visible, its place second: confirmed 0.65 of its contour,
    0.56 beyond chance, and not reported even at ``min_score`` 0.5).
    """
    if default_min_score <= 0.0:
        return 1.0
    return min(min_score / default_min_score, 1.0)


def _colour_rank(fit: _Fitted) -> float:
    """What fits compete by in a colour scene: the share of the contour
    confirmed plus COLOUR_WEIGHT times the relative colour agreement
    (:attr:`_Fitted.relative_colour`)."""
    return fit.detection.score + COLOUR_WEIGHT * fit.relative_colour


def _spare_locations(located: list[_Located], first: int, count: int) -> list[_Located]:
    """The spare locations: of the ``count`` after the first ``first`` (best
    first), those with at least SPARE_MIN_VIEW_EVIDENCE_SHARE of the best
    one's evidence."""
    if not located:
        return []
    floor = SPARE_MIN_VIEW_EVIDENCE_SHARE * located[0].evidence
    return [loc for loc in located[first: first + count] if loc.evidence >= floor]


def _supported(fits: list[_Fitted], locations: list[_Located],
               bar_share: float) -> list[_Fitted]:
    """The fits of colour locations (``fits[i]`` of ``locations[i]``) that
    may compete: a location whose views only the outline of the part's
    colour explains (:attr:`_Located.outline_only`) has no support from
    the photo's edges, and its fit is held to the spares' bar
    (:func:`_convincing` in colour, the bar times ``bar_share``)."""
    return [f for f, loc in zip(fits, locations, strict=True)
            if not loc.outline_only or _convincing(f, True, bar_share)]


def _evidence_share(fit: _Fitted, best: float) -> float:
    """The fit's location's view-search evidence as a share of ``best`` (0 when
    ``best`` is not positive)."""
    return fit.evidence / best if best > 0.0 else 0.0


def _ranked(fits: list[_Fitted], by_colour: bool = False) -> list[Detection]:
    """Detections best first, given in the view search's evidence order.

    Refined fits come first, ranked by their chance-corrected inlier fraction
    plus :data:`EVIDENCE_WEIGHT` times their location's view-search evidence as
    a share of the best fit's. A plain inlier fraction is high wherever texture
    offers edges of any orientation (hard bench set, 640x480 textured: ranked
    by it rather than in the view search's order, a wrong place beat the right
    one in 3 more of 80 images). Corrected for chance it is still not enough
    alone: a refinement started at a wrong place can settle on clutter and
    confirm its contour as well as the part (hard set, learning seeds 0-4,
    every located place fitted: of 400 images the right fit ranked first in 330
    by the former key, confirmed fits by their plain fraction first, and in 370
    with the evidence; the 46 wrong fits that won had a median 0.57 of the
    right location's evidence and hit fractions of median 0.5, the right ones
    0.87). The evidence weighs how well the training views explain the place
    before any fit, each edge sample against the image's own edge density. Fits
    whose refinement failed come last, in the view search's order.
    With ``by_colour`` (a colour cue), fits whose visible surface the
    part's colours do not explain (:data:`MIN_COLOUR_AGREEMENT`), whose
    contour and colour together fall short (:data:`MIN_COLOUR_RANK`) or
    beyond whose outline the part's rare colours run on
    (:data:`COLOUR_LEAK_MAX`) are dropped and the refined ones are ranked
    together by their inlier fraction plus :data:`COLOUR_WEIGHT` times
    their relative colour agreement (:attr:`_Fitted.relative_colour`),
    less the part's colour beyond their outline
    (:attr:`_Fitted.colour_leak_penalty`): on real photos in clutter a
    wrong place confirms its contour as well as the right one (LM-O:
    inlier fractions 0.6-0.94 at both). The view-search evidence changes
    nothing there (LM-O ape, can, cat: weights 0.1-0.5 gave the right
    detection in 0 to 2 more of 545 photos).
    Without the colour cue the key adds the figure-ground bonus
    (:attr:`_Fitted.figure_ground_bonus`): a cast shadow or a texture
    confirms an outline as well as the part, but encloses the colours
    around it.
    """
    if by_colour:
        fits = [f for f in fits
                if (f.colour_agreement or 0.0) >= MIN_COLOUR_AGREEMENT
                and _colour_rank(f) >= MIN_COLOUR_RANK and not f.leaks_rare_colour]
        refined = sorted((f for f in fits if f.detection.refined),
                         key=lambda f: -(_colour_rank(f) - f.colour_leak_penalty))
    else:
        best = max((f.evidence for f in fits), default=0.0)
        refined = sorted((f for f in fits if f.detection.refined),
                         key=lambda f: -((f.chance_corrected or 0.0) + f.figure_ground_bonus
                                         + EVIDENCE_WEIGHT * _evidence_share(f, best)))
    failed = [f for f in fits if not f.detection.refined]
    return [f.detection for f in refined + failed]


def _non_increasing(detections: list[Detection]) -> list[Detection]:
    """The detections with each score lowered to at most the one before it."""
    out: list[Detection] = []
    for det in detections:
        if out and det.score > out[-1].score:
            det = replace(det, score=out[-1].score)
        out.append(det)
    return out


def _centred_poses(detections: list[Detection],
                   origin_offset_mm: NDArray[np.float64]) -> list[Pose]:
    """The detections' poses in the centred frame the fits were made in (that
    of the surface samples): the model's origin moved by ``origin_offset_mm``
    (:attr:`ObjectModel.origin_offset_mm`)."""
    return [Pose(d.pose.R_m2c, d.pose.t_m2c + d.pose.R_m2c @ origin_offset_mm)
            for d in detections]


def _visible_first(detections: list[Detection], origin_offset_mm: NDArray[np.float64],
                   camera: Camera, samples: SurfaceSamples | None) -> list[Detection]:
    """The ranked detections, those that would lie hidden behind another
    which confirms more of its contour moved after the rest
    (:func:`viewloc_core.hidden_fits.lies_hidden_behind`; refined
    detections only, in their order).

    If the nearer part is there, the farther one cannot be seen; and the
    nearer one's contour is the better confirmed. A far copy of a large
    part fitted to the part's own inner edges shows nothing but the part's
    colours, and out-ranked the whole part in a colour scene (LM-O's
    driller rendered over plain grey, every 4th image: 15 of 54 first fits).
    ``origin_offset_mm`` is the model's (:attr:`ObjectModel.origin_offset_mm`),
    ``samples`` its surface samples in the centred frame the fits were made
    in (None: no surface, the detections as they are).
    """
    if samples is None or len(detections) < 2:
        return detections
    centred = _centred_poses(detections, origin_offset_mm)
    hidden = [d.refined and any(
        other.refined and other.score > d.score
        and lies_hidden_behind(camera, centred[i], centred[j], samples)
        for j, other in enumerate(detections) if j != i)
        for i, d in enumerate(detections)]
    return ([d for d, h in zip(detections, hidden, strict=True) if not h]
            + [d for d, h in zip(detections, hidden, strict=True) if h])


def _distinct(detections: list[Detection], model: ObjectModel, camera: Camera,
              surface: tuple[SurfaceSamples, NearSymmetries] | None,
              limit: int) -> list[Detection]:
    """The first ``limit`` of the ranked detections that are not a worse fit
    of a part already detected (:mod:`viewloc_core.distinct_parts`)."""
    if len(detections) < 2 or limit < 2:
        return detections[:limit]
    centred = _centred_poses(detections, model.origin_offset_mm)
    keep = distinct_parts(centred, camera, model.diameter_mm,
                          None if surface is None else surface[0], limit)
    return [detections[i] for i in keep]


def localize(
    model: ObjectModel,
    image: NDArray[np.generic],
    camera: Camera,
    options: LocalizeOptions = LocalizeOptions(),
) -> LocalizationResult:
    """Find an object in an image and return its 6D poses.

    Parameters
    ----------
    model : ObjectModel
        A learned model.
    image : (H, W) or (H, W, 3) array, uint8 or uint16
        The scene (RGB when colour).
    camera : Camera
        Intrinsics of the scene camera; its width and height must match the image.
    options : LocalizeOptions

    Returns
    -------
    LocalizationResult
        Detections best first; empty when nothing scores above ``min_score``.
    """
    t0 = time.perf_counter()
    scene = prepare_scene(image, camera, edges=refines(model, options))
    try:
        result = localize_in_scene(model, scene, options, deadline=options.deadline(t0))
    finally:
        scene.release()
    result.timing_ms["total"] = (time.perf_counter() - t0) * 1e3
    return result


def _search_config(model: ObjectModel, scene: Scene,
                   depth: DepthRange | None) -> AlignConfig | None:
    """The alignment's settings, its scales narrowed to the sizes the depth
    range allows (:meth:`DepthRange.scale_bounds`); None when it allows
    none of the searchable ones."""
    config = AlignConfig()
    if depth is None:
        return config
    least, greatest = depth.scale_bounds(
        scene.camera, scene.factor, model.d0_mm, model.f_train_px, model.diameter_mm,
        float(np.linalg.norm(model.origin_offset_mm)))
    least, greatest = max(least, config.min_scale), min(greatest, config.max_scale)
    if least >= greatest:
        return None
    return replace(config, min_scale=least, max_scale=greatest)


def _in_search_space(det: Detection, model: ObjectModel, camera: Camera,
                     options: LocalizeOptions) -> bool:
    """Whether a detection's centre lies in the request's region and its
    origin in its depth range (either holds when not given)."""
    if options.depth_mm is not None and not options.depth_mm.holds(det):
        return False
    if options.roi is None:
        return True
    centre_cam = det.pose.R_m2c @ model.origin_offset_mm + det.pose.t_m2c
    if centre_cam[2] <= 0:
        return False
    return bool(options.roi.contains(camera.project(centre_cam[None]))[0])


def _in_region(loc: _Located, factor: float, roi: ImageRegion | None) -> bool:
    """Whether a location's best view lies within :data:`REGION_SLACK_PX`
    of the request's region (the view search may have moved it off the
    alignment's place), or there is no region. A location outside is not
    fitted. Its depth is not judged before the fit: the view search's
    scale can be far off where the refinement finds the part (hard set,
    the truth's depth +-15 % and a location more than 15 % beyond it left
    unfitted: bracket AR_MSSD 0.855 -> 0.805)."""
    return roi is None or bool(roi.contains(loc.candidates[0].sim[None, :2], factor,
                                            REGION_SLACK_PX)[0])


def localize_in_scene(model: ObjectModel, scene: Scene,
                      options: LocalizeOptions = LocalizeOptions(),
                      deadline: float | None = None) -> LocalizationResult:
    """:func:`localize` in a scene already prepared (:func:`prepare_scene`),
    perhaps shared with other parts.

    The scene is searched on its pyramid level (:data:`MAX_SEARCH_SIDE_PX`).
    When no fit found there resolves the part's outline (:func:`_resolved`:
    it settled, or it confirms :data:`FINER_SEARCH_NEEDLESS_FRACTION` of its
    contour plainly and beyond chance) and the image is
    larger than the level, it is searched again on a finer level
    (:meth:`Scene.at_finer_level`, the full image up to 640x480); that
    search's detections replace the level's when its best fit settles and
    ranks higher (:func:`_answer_rank`). A thin part (a shaft, a bolt's
    shank) can be a few pixels wide on the coarse level, where the two
    sides of its outline blur into one edge; a fine texture, on the other
    hand, swamps the part's outline at full resolution (see
    :data:`MAX_SEARCH_SIDE_PX`), so the finer search must settle to
    overrule. Where the part's colours are a cue, fits are ranked by
    them, not by settling, and the colour proposes places of its own
    (:func:`_colour_locations`): there the image is searched once.

    Bench, learning seed 0, against the level alone: shop set (a bolt, a
    shaft, a thin plate) rec2D 0.75 -> 0.79, AR_MSSD / AR_MSPD 0.652 /
    0.693 -> 0.709 / 0.743; hard 0.9625 -> 0.975, 0.909 / 0.929 -> 0.921
    / 0.941; novel 0.942 -> 0.958, 0.885 / 0.898 -> 0.909 / 0.923; no
    part-free image given a detection it did not have. Taking the finer
    search's answer whenever it ranked higher, settled or not, gave
    part-free hard images 6 -> 9 of 12 detections. On LM-O's colour photos
    (objects 1, 5, 6, 8) the finer search ran on 700 of 745 (real clutter
    rarely settles a fit), replaced 17 answers, and changed AR_MSSD /
    AR_MSPD from 0.187 / 0.260 to 0.185 / 0.259 at 2.3-2.6 times the
    median latency (two runs beside other jobs): it is not run in colour.

    With a time budget (``options.timeout_ms``), none of the searches that
    only look further for the part is started unless it is expected to end
    within the budget: the finer level's (expected to take the level's
    search time, features included, times the ratio of their pixels), the
    spare locations' fits (the first fits' time per round on the two
    cores) and further locations' (the last round's). A QA cycle has a
    fixed time, as HALCON's ``timeout`` parameter of its shape matching
    gives. What was found before is the answer, and the result says that
    the search was cut short. The stages' times on a 640x480 image (hard
    bench set, medians) are about 16 ms of features, 15 ms of alignment,
    8 ms of view search and 22 ms of fits; the finer level's search, where
    it runs, another 110-150 ms.

    Parameters
    ----------
    model : ObjectModel
        A learned model.
    scene : Scene
        The image, its camera, features and edge pyramid.
    options : LocalizeOptions
    deadline : float, optional
        :func:`time.perf_counter` time at which the budget is spent; by
        default ``options.timeout_ms`` from now (a caller that prepared the
        scene, or searches several parts in it, passes its own).

    Returns
    -------
    LocalizationResult
        Detections best first; empty when nothing scores above ``min_score``.
        Its ``timing_ms`` gives the scene's ``features`` time, and a
        ``total`` without it; ``finer_search`` when the image was
        searched again on the finer level (its features, search and fits).
    """
    t0 = time.perf_counter()
    budget = _Budget(options.deadline(t0) if deadline is None else deadline)
    answer = _localize_on_level(model, scene, options, budget)
    timing = answer.timing_ms
    if (refines(model, options) and scene.has_finer_level() and not answer.in_colour
            and (answer.best is None or not _resolved(answer.best))
            and budget.allows(_finer_search_expected_s(scene, time.perf_counter() - t0))):
        t1 = time.perf_counter()
        again = _localize_on_level(model, scene.at_finer_level(), options, budget)
        timing["finer_search"] = (time.perf_counter() - t1) * 1e3
        if (again.best is not None and _settled(again.best)
                and (answer.best is None
                     or _answer_rank(again.best) > _answer_rank(answer.best))):
            answer = again
    timing["total"] = (time.perf_counter() - t0) * 1e3
    return LocalizationResult(answer.detections, timing, budget.cut_short)


def _finer_search_expected_s(scene: Scene, level_search_s: float) -> float:
    """The time the finer level's search of ``scene`` is expected to take,
    seconds: the level's, features included, times the ratio of the two
    levels' pixels (the search's stages grow with the pixels). On the hard
    bench set that expects about 150 ms where the finer search took 108 ms
    (median): an overestimate, so a budget leaves the search out rather
    than overrun."""
    finer_factor = _level_factor(scene.image, FINER_SEARCH_SIDE_PX)
    pixel_ratio = (finer_factor / scene.factor) ** 2
    return (scene.features_ms / 1e3 + level_search_s) * pixel_ratio


@dataclass(eq=False, slots=True)
class _Budget:
    """A localization's time budget: whether a further search may start.

    Attributes
    ----------
    deadline : float
        :func:`time.perf_counter` time at which it is spent (``inf``: never).
    cut_short : bool
        Whether a search was left out because it was not expected to end
        within it.
    """

    deadline: float
    cut_short: bool = False

    def allows(self, expected_s: float = 0.0) -> bool:
        """True when a search expected to take ``expected_s`` seconds ends
        within the budget; else notes that a search is left out."""
        if time.perf_counter() + expected_s < self.deadline:
            return True
        self.cut_short = True
        return False


@dataclass(frozen=True, slots=True, eq=False)
class _LevelAnswer:
    """What the search of one level of a scene answers.

    Attributes
    ----------
    detections : list of Detection
        Best first.
    best : _Fitted or None
        The fit of the first detection; None when there is none.
    in_colour : bool
        Whether the part's colours were a cue: fits were ranked by them
        (:func:`_ranked`).
    timing_ms : dict of str to float
        The stages' times, ms.
    """

    detections: list[Detection]
    best: _Fitted | None
    in_colour: bool
    timing_ms: dict[str, float]


def _answer_rank(fit: _Fitted) -> float:
    """How a search's best fit compares with another search's of the same
    image where the part's colours are no cue (:func:`localize_in_scene`):
    its refinement's inlier fraction corrected for chance plus the
    figure-ground bonus, as :func:`_ranked` orders such fits, without the
    view search's evidence, which each level measures on its own edges. A
    fit whose refinement failed ranks below every refined one."""
    if not fit.detection.refined:
        return -1.0
    return (fit.chance_corrected or 0.0) + fit.figure_ground_bonus


def _localize_on_level(model: ObjectModel, scene: Scene, options: LocalizeOptions,
                       budget: _Budget) -> _LevelAnswer:
    """The search and fits of :func:`localize_in_scene` on the scene's level."""
    t2 = time.perf_counter()
    arr, camera, factor, level = scene.image, scene.camera, scene.factor, scene.level
    feats, chance = scene.features, scene.chance
    index = model_index(model)
    timing: dict[str, float] = {"features": scene.features_ms}
    contour = _contour_model(model) if refines(model, options) else None
    if options.roi is not None:
        options.roi.check_within(camera.width, camera.height)
    config = _search_config(model, scene, options.depth_mm)
    if config is None:
        return _LevelAnswer([], None, False, timing)
    # Hypotheses are placed by the part's centre; a few level pixels of
    # slack keep those of a part centred at the region's edge (the final
    # fits are held to the region itself, _in_search_space).
    within = (None if options.roi is None
              else options.roi.bounds(factor, REGION_SLACK_PX))
    matches = align(model, index, feats, config,
                    max_matches=max(MIN_ALIGNED_LOCATIONS,
                                    ALIGNED_LOCATIONS_PER_DETECTION * options.max_detections + 1),
                    chance=chance, within=within)
    # The locations beyond the detections wanted are spares, in case the
    # alignment ranked a false one first; a spare with under half the best
    # location's evidence practically never wins the view search (bench,
    # 180 images: the same winners), so it is not searched.
    matches = matches[: options.max_detections] + [
        m for m in matches[options.max_detections:]
        if m.evidence >= SPARE_EVIDENCE_SHARE * matches[0].evidence]
    t3 = time.perf_counter()
    timing["align"] = (t3 - t2) * 1e3

    min_score = model.default_min_score if options.min_score is None else options.min_score
    # The spares' bar, and the further detections' (_after_the_first_convincing).
    bar_share = _spare_bar_share(min_score, model.default_min_score)
    # Pass 1: per image location, the training views that explain it best.
    templates = view_templates(model)
    located = []
    surface = _surface(model) if contour is not None else None
    n_candidates = _view_candidate_count(surface)
    # Only fits that read the part's surface compare its sides (_other_sides).
    other_side = (OTHER_SIDE_CANDIDATES if surface is not None and _compares_sides(model)
                  else 0)
    for match in matches:
        seeds = np.array([best_member(model, m.model_view, m.sim, feats)[1]
                          for m in (match, *match.alternatives)])
        located.append(_Located(match, search_views(feats, templates, seeds, chance,
                                                    n_candidates, other_side=other_side)))
    located = [loc for loc in located if loc.candidates
               and _in_region(loc, factor, options.roi)]
    located.sort(key=lambda loc: -loc.evidence)
    colour = _ColourScene.of(model, level, factor) if contour is not None else None
    # The colour windows keep the whole scale range, also under a depth
    # range: a window's size says little about the part's scale (LM-O, the
    # depth of the truth +-15 %: windows over the narrowed range proposed
    # worse places, AR_MSSD 0.174 -> 0.166; over the whole range 0.175).
    # What they propose outside the range is not reported (answer below).
    colour_located = ([] if colour is None else
                      [loc for loc in _colour_locations(
                          model, colour, feats, templates, chance, AlignConfig(),
                          located[: options.max_detections], within, other_side)
                       if _in_region(loc, factor, options.roi)])
    t4 = time.perf_counter()
    timing["views"] = (t4 - t3) * 1e3
    # Nothing to refine: the pyramid is not waited for (nor built, if not
    # started, once the scene is released).
    edges = scene.edges() if contour is not None and (located or colour_located) else None
    # Pass 2: the final fit of the best locations, as many as detections are
    # wanted. When one of them is not settled, the view search may have
    # ranked a wrong place first: the next SPARE_LOCATIONS locations are
    # fitted too and the refinements and the evidence decide (_ranked).
    # Hard bench set, learning seeds 0-4 (400 images), one spare -> two with
    # the evidence in the ranking: right detections 351 -> 361, AR_MSSD mean
    # 0.778 -> 0.799; later three spares, with the settling rule and the
    # alignment's gate as now: 0.822 -> 0.8305. Settled fits need no spare,
    # which keeps the cost to the doubtful images, unless they enclose the
    # colours around them (_settled: a cast shadow confirms the part's
    # outline); without refinement nothing would overrule the view search's
    # order.
    shading = None
    if edges is not None and surface is not None:
        interior = (_Interior(feats.edge_distance, factor, contour)
                    if contour is not None
                    and contour.crease_share() >= INTERIOR_EDGE_MIN_CREASE_SHARE else None)
        shading = _Shading(arr, *surface, colour, interior)
        if colour is not None:
            # The part's colour boundary is an edge for every fit in this
            # image (:mod:`viewloc_core.colour_edges`).
            edges = with_colour_boundary(edges, colour.full_posterior(arr))
    else:
        colour = None

    def fit(loc: _Located) -> _Fitted:
        return _final_detection(model, loc, level, factor, camera, edges, contour,
                                index.view_radius_px, shading)

    # The fits are independent and their refinements compiled: they share
    # the two cores (LM-O, colour locations: pose stage 65 -> 57 ms median).
    first = located[: options.max_detections]
    # Colour locations compete with the alignment's by the colour under the
    # fit (see _ranked).
    colour_fitted = colour_located if colour is not None else []
    t_fits = time.perf_counter()
    fitted = each_on_both(fit, first + colour_fitted)
    # A round of fits: one on each core.
    round_s = (time.perf_counter() - t_fits) / max(1, math.ceil(len(first + colour_fitted) / 2))
    fits, colour_fits = fitted[:len(first)], fitted[len(first):]
    spares: list[_Located] = []
    # A fit outside the request's region or depth range is not an answer,
    # however well it settled.
    if (contour is not None and len(located) > options.max_detections
            and not all(_settled(f) and _in_search_space(f.detection, model, camera, options)
                        for f in fits)):
        in_colour = colour is not None
        n_spares = SPARE_LOCATIONS_IN_COLOUR if in_colour else SPARE_LOCATIONS
        spares = _spare_locations(located, options.max_detections, n_spares)
        if budget.allows(round_s * math.ceil(len(spares) / 2)):
            fits += [f for f in each_on_both(fit, spares)
                     if _convincing(f, in_colour, bar_share)]
        else:
            spares = []
    fits += _supported(colour_fits, colour_fitted, bar_share)

    def answer() -> list[Detection]:
        """The first max_detections of the ranked fits that are each a part
        of its own (:func:`_distinct`), those after the first as convincing
        as a spare's (:func:`_after_the_first_convincing`, refined fits)."""
        # A fit whose rotation is undetermined is not reported, but it does
        # not send the search on to further places either: fitting more
        # places found other chance fits on part-free images (paper, hard
        # and novel sets, limit 20°: 21 of 34 reported instead of 19) and
        # no right one.
        ranked = _visible_first(
            _ranked([f for f in fits if f.detection.score >= min_score
                     and f.determined(options.rotation_std_limit_deg)
                     and _in_search_space(f.detection, model, camera, options)],
                    by_colour=colour is not None), model.origin_offset_mm, camera,
            None if surface is None else surface[0])
        if contour is not None and options.max_detections > 1:
            ranked = _after_the_first_convincing(ranked, fits, colour is not None, bar_share)
        return _distinct(ranked, model, camera, surface, options.max_detections)

    detections = answer()
    # With more than one detection wanted, places the first fits left free
    # (fits of one part twice, fits under min_score) go to the next
    # locations not yet fitted, as many at a time as places are free, until
    # none is left. One detection wanted has its spares (above) instead,
    # unless the request bounds the search and a fit good enough to be the
    # answer lay outside the bounds: a part at another depth can fit better
    # than the one asked for, and take the spares' evidence floor with it.
    # Then up to SPARE_LOCATIONS more are fitted, two at a time (one on each
    # core). That costs time where wrong fits at other depths are common:
    # LM-O every 4th photo with the depth of the truth +-15 %, pose stage
    # median 109 -> 148 ms, the same AR (0.175 / 0.233).
    fitted_locations = {id(loc) for loc in first + spares}
    unfitted = [loc for loc in located if id(loc) not in fitted_locations]
    if options.max_detections == 1:
        unfitted = unfitted[:SPARE_LOCATIONS]

    def fills(batch: list[_Fitted]) -> bool:
        return options.max_detections > 1 or any(
            f.detection.score >= min_score
            and not _in_search_space(f.detection, model, camera, options) for f in batch)

    go_on = fills(fits)
    least_batch = 1 if options.max_detections > 1 else 2
    while go_on and len(detections) < options.max_detections and unfitted:
        batch = unfitted[: max(least_batch, options.max_detections - len(detections))]
        if not budget.allows(round_s * math.ceil(len(batch) / 2)):
            break
        unfitted = unfitted[len(batch):]
        t_batch = time.perf_counter()
        batch_fits = each_on_both(fit, batch)
        round_s = (time.perf_counter() - t_batch) / math.ceil(len(batch) / 2)
        fits += batch_fits
        detections = answer()
        go_on = fills(batch_fits)
    if (edges is not None and shading is not None and contour is not None and detections
            and _compares_sides(model)):
        # Each reported detection's location of a part with colours of its
        # own gets a wider look: more views compete with its fit
        # (_wider_look). Learning seed 0, LM-O objects 1, 5, 6, 8: AR_MSSD /
        # AR_MSPD 0.148 / 0.208 -> 0.157 / 0.217, right places turned
        # 15 % -> 12 %; held-out objects 9-12: 0.165 / 0.238 -> 0.180 /
        # 0.251, turned 20 % -> 14 %; pose stage +18 ms median (two runs at
        # once). The parts without colours gain less for the cost (hard
        # bench set 0.909 / 0.929 -> 0.921 / 0.941, novel the same, pose
        # stage +12 to +19 ms against a budget of 60 ms an image).
        by_detection = {id(f.detection): f for f in fits}
        reported = [by_detection[id(d)] for d in detections]
        looked = each_on_both(partial(_wider_look, model, feats, chance, factor, camera, edges,
                                      contour, shading), reported)
        swap = {id(old): new for new, old in zip(looked, reported, strict=True)
                if new is not old}
        if swap:
            fits = [swap.get(id(f), f) for f in fits]
            detections = answer()
    # Scores do not rise down the list: a detection ranked below another is
    # reported with no more quality than it (never under min_score: the
    # one above is at least that).
    best = None
    if detections:
        best = next(f for f in fits if f.detection is detections[0])
    detections = _non_increasing(detections)
    timing["pose"] = (time.perf_counter() - t4) * 1e3
    return _LevelAnswer(detections, best, colour is not None, timing)

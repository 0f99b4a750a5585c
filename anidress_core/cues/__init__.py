"""2D cues for garment fitting (DESIGN.md §7): masks, optical flow, their errors.

* :mod:`.masks`: body + garment label masks from images, background plates and a
  shape prior (the posed body and the skinned garment template);
* :mod:`.flow`: forward optical flow t-1 -> t with OpenCV, inside the subject's box;
* :mod:`.evaluate`: IoU, end-point error and normal angular error against ground truth.

Normal maps are not estimated: they come with the data (an external predictor;
the synthetic scenes ship degraded true normals) and are used as they are.
"""
from .evaluate import CueErrors, angle_sums, epe_sums, iou_counts
from .flow import FLOW_METHODS, FlowEstimate, Region, estimate_flow, flow_region, make_estimator, to_gray8
from .masks import (MASK_METHODS, MaskParams, colour_distance, estimate_masks, fit_colour_model, foreground,
                    label_colour, label_grabcut, label_prior, prior_distances, render_prior, subject_masks,
                    temporal_median_plate)

__all__ = [
    "CueErrors", "angle_sums", "epe_sums", "iou_counts",
    "FLOW_METHODS", "FlowEstimate", "Region", "estimate_flow", "flow_region", "make_estimator", "to_gray8",
    "MASK_METHODS", "MaskParams", "colour_distance", "estimate_masks", "fit_colour_model", "foreground",
    "label_colour", "label_grabcut", "label_prior", "prior_distances", "render_prior", "subject_masks",
    "temporal_median_plate",
]

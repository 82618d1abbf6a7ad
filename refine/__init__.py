"""The refinement job (``python -m refine``, also ``fsof-refine``).

Reads image pairs (a rendered synthetic sequence by default, a folder of images, or the shared
KITTI samples), gets a flow for each pair (OpenCV DIS, the test net, or files written by any
network), refines it with the freespace model inside the road mask using given odometry (the
scene's, or poses) and/or ego-motion fitted to the flow or to the images, and writes the refined
flows (KITTI PNG), figures and a report (Markdown + JSON) of photometric error (census distance,
SSIM and L1) and, where ground truth exists, end-point error, inside the road and overall, before
and after.

Modules: ``inputs`` (what a pair is and where pairs come from), ``sources`` (flow sources),
``job`` (the loop, outputs), ``measure`` (the maps and metrics of a flow), ``report`` (pooling and
the report), ``options`` (the command line's parser and defaults), ``configure`` (the options
checked and turned into the run's pairs, camera, sources and variants), ``__main__`` (the run,
``main(argv=None) -> int``). The job imports only the library (``fsof_torch``).
"""

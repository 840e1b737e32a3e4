"""Cycles (Blender) as a second renderer of training data: what Blender users' files look like.

Optional (``pip install 'mcdenoise[blender]'``: ``bpy`` 4.5, Python 3.11). Our Mitsuba renderer
writes first-hit albedo and normals in world space and 0 on a miss; Cycles writes albedo and
normal that follow mirror and glass bounces, emission in the albedo and camera-space normals
(:mod:`mcdenoise.io.blender`), with its own sampler's noise. A model judged on Blender files is
best trained and validated on such files, and these modules make them:

``recipe``   the render settings of docs/DENOISE.md's Blender 4.x recipe plus ours (deterministic)
``draw``     a random scene description from (seed, index), plain Python (no ``bpy``)
``build``    that description built with ``bpy``
``worker``   one scene rendered at each input spp and the reference, in its own process
``dataset``  the dataset command: scenes rendered, converted to image folders, a manifest

``bpy`` runs only in the worker process: it bundles its own Open Image Denoise and TBB, which must
not meet pyoidn's.
"""

"""The splatting maths of the built-in primitives as readable torch: the torch twins.

    kernels.py    the α of one ray through one primitive: the neural line integral in closed form
                  (paper eq. 7-9, windowed and hard-edged) and the Gaussian's EWA footprint
    view.py       what every view needs: the frame of numbers, rays through image points, the
                  pixel bounds of an ellipsoid (its dual conic)
    neural.py     the neural primitive's per-view tensors and its pair kernel
    gaussian.py   the Gaussian's EWA projection, 3σ bounds and pair kernel
    sh.py         view-dependent colour from spherical harmonics
    composite.py  front-to-back compositing (paper eq. 4) of depth-ordered pairs

The kinds (core/kinds) assemble their renderer hooks from these, and the fast backends
(core/backends: fused C++, Triton) compute the same and are tested against them. Nothing here
knows the kind registry or the renderer's entry point (core/render)."""

"""One photo represented by 2D splats whose image is their plain sum (`splatk image`).

``model`` (:class:`~splatk.image.model.Splats2D`), ``kernels`` (gaussian, gabor, learned: the 2D
kernels by name), ``bytes`` (what the byte budget pays for), ``file`` (``splats.bin``: exactly
those bytes), ``fit`` (the fit loop), ``pictures`` (outlines and kernel mosaics).
"""

"""2D splats that represent one image (:class:`Splats2D`): Gaussian, Gabor, GabSplat and learned kernels.

All but GabSplat (rotation-scale, as its authors'; :class:`~splatk.image.kernels.GabSplatKernel2D`)
share the geometry of GaussianImage (Zhang et al. 2024; peers.md Sec. 7.1): a mean
``xy`` (``tanh`` of a raw value, so [-1, 1] maps to the image), a lower-triangular Cholesky
factor ``L = [[l11, 0], [l21, l22]]`` of the covariance in pixels (``Sigma = L L^T``) and an
RGB colour. The image is the plain sum (no alpha compositing)::

    I(x) = sum_i c_i k_i(u_i(x), v_i(x))          (GaussianImage "rasterize_gaussians_sum")

where ``(u, v) = L^-1 (x - mu) / 3`` are the splat's local coordinates: the 3-sigma ellipse is
the unit disk, which is also each kernel's support (3 sigma, as GaussianImage).

The kernels k(u, v) (gaussian, gabor, gabsplat, learned, learned-paper) are in :mod:`splatk.image.kernels`. The learned one
may also be stored with a shape palette:

* ``learned`` with a shape palette (``shapes = K``, 1 to 256): the same kernel, but what is
  stored is K shared latents (the palette) and one byte per splat naming its shape. Training
  keeps a free latent per splat for its first part, then k-means them into K palette entries
  (:meth:`Splats2D.quantize_shapes`) and trains the palette from there: a splat keeps a shape of
  its own choosing at a quarter of a float instead of L floats.  8 floats + 2 bytes

Learned-kernel choices (the paper leaves them open for images):

* A turn per splat: the learned shape is drawn at ``R(theta_i) (u, v)``, with ``theta_i`` stored
  in one byte (256 steps over 2 pi). The Cholesky frame ties the shape's axes to the image's x
  axis (``u = dx / l11``), so without a turn a shape that is not radially symmetric (an edge, a
  lobe on one side) can point only where the palette happens to hold a copy of it. Turning the
  shape with the ellipse's own axes instead (a rotation-scale covariance) gained next to nothing
  (docs/decisions/0008-image-learned-kernel.md has the measurements).
  Training renders the rounded angle and passes the gradient straight through to the float, so
  the image trained is the image stored.
* Signed output, no sigmoid: the image is a sum, not a composite, so a kernel may have negative
  lobes (as Gabor's do) and the sigmoid's [0, 1] range would forbid them.
* The network output multiplies the Gaussian envelope instead of standing alone: a free MLP is
  not zero at the edge of the support, which shows as a seam at every splat's bbox; ``E``
  makes the support as soft as the baseline's. The last layer starts at weight 0, bias 1, so
  at init the kernel *is* the Gaussian (what pretraining on Gaussian surfels aims at; paper
  Sec. 4.5) and the latents steer it away from there. A flatter envelope, ``(1 - r^2)^2``, or a
  learned width of the Gaussian one did worse (decision 0008; the learned width stayed within 8%
  of the Gaussian's).
* Table mode (default): the decoder is sampled per primitive on a ``G x G`` grid of nodes over
  (u, v) in [-1, 1]^2 and pixels interpolate bilinearly (the 2D analogue of paper Eq. 8), so
  per-pixel cost is one Gaussian plus four gathers. ``exact`` mode calls the decoder per pixel
  (the reference the table is tested against).

Rendering (``backend``): ``torch`` lists every (splat, pixel) pair inside the splat's 3-sigma
bbox (integers, no grad), evaluates the kernel on the pairs and sums the colours with
``index_add``, in chunks so the pairs in flight stay bounded; it is the reference, runs on any
device and also serves the ``exact`` learned mode. ``cpu`` hands the same boxes and transformed
parameters to the native op (the backend's ``render_image_splats``, ``backends/image_cpu.py``,
OpenMP, same image and gradients, several times faster); ``auto`` picks ``cpu`` when it builds and
the splats are on the CPU.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor, nn

from .. import backends
from ..backends import Backend
from .bytes import SHARED_DTYPE, bytes_per_primitive, check_shapes, network_bytes
from .kernels import LATENT_DIM, SUPPORT_SIGMAS, TURN_STEPS, image_kernel

BACKENDS = ("auto", "torch", "cpu")
#: largest bbox half-size in pixels (bounds the pairs of a huge splat; its tail is cut there)
MAX_RADIUS = 64
#: (splat, pixel) pairs evaluated at once
CHUNK_PAIRS = 2_000_000


def kmeans(points: Tensor, k: int, generator: torch.Generator | None = None, steps: int = 50) -> tuple[Tensor, Tensor]:
    """Lloyd's k-means with k-means++ seeding: ``points`` [N, D] -> (centres [k', D], labels [N]);
    k' = min(k, N). An emptied cluster is re-seeded at the point farthest from its centre."""
    n = points.shape[0]
    k = min(int(k), n)
    first = int(torch.randint(n, (1,), generator=generator))
    centres = points[first:first + 1].clone()  # updated in place below; points stay as given
    for _ in range(1, k):
        d2 = torch.cdist(points, centres).min(1).values ** 2
        # a point already picked has weight 0; all-zero weights (duplicates) fall back to uniform
        w = d2 if float(d2.sum()) > 0 else torch.ones_like(d2)
        centres = torch.cat([centres, points[torch.multinomial(w, 1, generator=generator)]])
    labels = torch.cdist(points, centres).argmin(1)
    for _ in range(steps):
        for j in range(k):
            members = labels == j
            if members.any():
                centres[j] = points[members].mean(0)
            else:
                centres[j] = points[torch.cdist(points, centres).min(1).values.argmax()]
        new = torch.cdist(points, centres).argmin(1)
        if torch.equal(new, labels):
            break
        labels = new
    return centres, labels


class Splats2D(nn.Module):
    """N 2D splats of one kernel kind fitted to an H x W image.

    Args:
        kernel: a name of :data:`~splatk.image.kernels.KERNELS`.
        n: number of primitives.
        height, width: image size in pixels.
        grid: table nodes per axis of the learned kernel (4 to 8 are sensible).
        exact: learned kernel only: evaluate Phi_dec_planar per pixel instead of the table.
        latent_dim: learned kernel only: floats of each primitive's latent z.
        shapes: learned kernel only: size of the shape palette that :meth:`quantize_shapes`
            makes (0: every splat keeps its own latent; see the module docstring).
        generator: for the random init (means uniform, colours uniform in [0, 0.1]).
    """

    def __init__(self, kernel: str, n: int, height: int, width: int, grid: int = 8,
                 exact: bool = False, generator: torch.Generator | None = None,
                 latent_dim: int = LATENT_DIM, backend: str = "auto", shapes: int = 0):
        super().__init__()
        if backend not in BACKENDS:
            raise ValueError(f"unknown image backend {backend!r}; choose from {', '.join(BACKENDS)}")
        self.backend = backend
        self.kernel2d = image_kernel(kernel)
        if n < 1:
            raise ValueError(f"need at least one primitive, got {n}")
        self.kernel, self.n, self.height, self.width = kernel, int(n), int(height), int(width)
        self.grid, self.exact = int(grid), bool(exact)
        if self.kernel2d.decoded and latent_dim < 0:
            raise ValueError(f"latent_dim must be >= 0, got {latent_dim}")
        self.latent_dim = int(latent_dim)
        check_shapes(int(shapes))
        self.shapes = int(shapes) if kernel == "learned" else 0
        # set by quantize_shapes: the palette [K, L] and each splat's entry in it
        self.palette: nn.Parameter | None = None
        self.register_buffer("shape_index", None)
        gen = generator
        self.xy_raw = nn.Parameter(torch.atanh(torch.rand(n, 2, generator=gen) * 1.96 - 0.98))
        # initial sigma: splats tile the image about twice over
        self.s0 = 0.5 * math.sqrt(height * width / n)
        self.kernel2d.init_geometry(self, n, self.s0)  # chol; gabsplat: sigmas and angle
        self.colors = nn.Parameter(torch.rand(n, 3, generator=gen) * 0.1)
        # gabor: gabor_amps, gabor_freqs; gabsplat: wave_coeffs; learned: latents, decoder, turn
        self.kernel2d.init_params(self, n, latent_dim, gen)

    # ---- geometry -------------------------------------------------------------------------
    def means_px(self) -> Tensor:
        """[N, 2] means in pixels (x, y), pixel centres at integer + 0.5."""
        t = (torch.tanh(self.xy_raw) + 1.0) * 0.5
        return t * torch.tensor([self.width, self.height], dtype=t.dtype, device=t.device)

    def chol_factors(self) -> tuple[Tensor, Tensor, Tensor]:
        """l11, l21, l22 of the covariance's Cholesky factor in pixels, sigmas >= 0.3 px (no
        degenerate splats)."""
        return self.kernel2d.chol_factors(self)

    @torch.no_grad()
    def quantize_shapes(self, generator: torch.Generator | None = None) -> None:
        """Replace the per-splat latents by a palette of ``shapes`` entries: k-means of the
        latents, each splat pointing at its nearest centre. From here on the palette is the
        trained parameter and ``latents`` is unused."""
        if self.kernel != "learned" or not self.shapes:
            raise ValueError("quantize_shapes needs the learned kernel with shapes > 0")
        # k-means on the CPU: the seeded generator is a CPU one, whatever the model's device
        centres, labels = kmeans(self.latents.detach().cpu(), self.shapes, generator)
        self.palette = nn.Parameter(centres.to(self.latents.device))
        self.shape_index = labels.to(self.latents.device)

    @torch.no_grad()
    def round_shared(self) -> None:
        """Round a learned kernel's shared decoder and palette to :data:`SHARED_DTYPE`, the
        precision the file stores them at (values stay float32 tensors)."""
        if not self.kernel2d.decoded:
            return
        shared = list(self.decoder.parameters()) + ([self.palette] if self.palette is not None else [])
        for p in shared:
            p.copy_(p.to(SHARED_DTYPE).to(p.dtype))

    def splat_latents(self, idx: Tensor | None = None) -> Tensor:
        """[N or P, L] the latent each splat draws with (its palette entry once quantized)."""
        if self.palette is None:
            return self.latents if idx is None else self.latents[idx]
        index = self.shape_index if idx is None else self.shape_index[idx]
        return self.palette[index]

    def turn_steps(self) -> Tensor:
        """[N] each learned splat's turn as its stored byte: steps of 2 pi / TURN_STEPS (float)."""
        return torch.round(self.turn.detach() / (2.0 * math.pi / TURN_STEPS)) % TURN_STEPS

    def turns(self) -> Tensor:
        """[N] each learned splat's turn as stored (rounded to one of TURN_STEPS); the gradient
        passes straight through the rounding to the float parameter."""
        stored = self.turn_steps() * (2.0 * math.pi / TURN_STEPS)
        # written so the value is exactly ``stored`` (turn - turn is 0 in floats; the other order
        # is off by an ulp), so the stored file redraws the trained image bit for bit
        return stored + (self.turn - self.turn.detach())

    @staticmethod
    def turned_uv(uv: Tensor, turn: Tensor) -> Tensor:
        """R(turn) uv for uv [..., 2] and turn broadcast against uv[..., 0]."""
        c, s = torch.cos(turn), torch.sin(turn)
        u, v = uv[..., 0], uv[..., 1]
        return torch.stack([c * u - s * v, s * u + c * v], -1)

    def kernel_table(self) -> Tensor:
        """[N, G, G] Phi_dec_planar at each splat's turned grid nodes (learned kernel): the table
        is per splat, so pixels look the shape up in the splat's (u, v) as the other kernels do."""
        g = torch.linspace(-1.0, 1.0, self.grid, dtype=self.latents.dtype, device=self.latents.device)
        vv, uu = torch.meshgrid(g, g, indexing="ij")
        uv = torch.stack([uu, vv], -1).reshape(1, -1, 2)  # [1, G*G, 2]
        turned = self.turned_uv(uv, self.turns()[:, None])  # [N, G*G, 2]
        out = self.decoder(turned, self.splat_latents()[:, None, :])  # [N, G*G]
        return out.reshape(self.n, self.grid, self.grid)

    def _extras(self) -> Tensor:
        """[N, E] the kernel's own per-primitive values packed for one gather (E may be 0)."""
        return self.kernel2d.extras(self)

    def kernel_values(self, uv: Tensor, idx: Tensor, table: Tensor | None = None,
                      extras: Tensor | None = None) -> Tensor:
        """k(u, v) for samples ``uv`` [P, 2] of primitives ``idx`` [P] -> [P] (0 outside the disk).

        ``extras`` [P, E] are the gathered :meth:`_extras` rows (gathered here when None).
        """
        return self.kernel2d.values(self, uv, idx, table, extras)

    # ---- rendering ------------------------------------------------------------------------
    @torch.no_grad()
    def _boxes(self, means: Tensor, l11: Tensor, l21: Tensor, l22: Tensor):
        """Each splat's pixel box around its 3-sigma ellipse: x0, y0 (int32) and radii rx, ry;
        the box is x0 .. x0 + 2 rx, y0 .. y0 + 2 ry (may reach outside the image)."""
        rx = (SUPPORT_SIGMAS * l11).ceil().clamp(max=MAX_RADIUS).int()
        ry = (SUPPORT_SIGMAS * torch.sqrt(l21 * l21 + l22 * l22)).ceil().clamp(max=MAX_RADIUS).int()
        x0 = means[:, 0].floor().int() - rx
        y0 = means[:, 1].floor().int() - ry
        return x0, y0, rx, ry

    @torch.no_grad()
    def _pairs(self, means: Tensor, l11: Tensor, l21: Tensor, l22: Tensor):
        """(splat index, pixel x, pixel y) for every pixel centre in each splat's 3-sigma bbox."""
        x0, y0, rx, ry = self._boxes(means, l11, l21, l22)
        wx = 2 * rx + 1
        counts = (wx * (2 * ry + 1)).long()
        dev = means.device
        idx = torch.repeat_interleave(torch.arange(self.n, dtype=torch.int32, device=dev), counts)
        starts = (torch.cumsum(counts, 0) - counts).int()
        k = torch.arange(int(counts.sum()), dtype=torch.int32, device=dev) - torch.repeat_interleave(starts, counts)
        wxp = torch.repeat_interleave(wx, counts)
        px = torch.repeat_interleave(x0, counts) + k % wxp
        py = torch.repeat_interleave(y0, counts) + k // wxp
        keep = (px >= 0) & (px < self.width) & (py >= 0) & (py < self.height)
        return idx[keep].long(), px[keep], py[keep]

    def resolve_backend(self) -> Backend:
        """The backend named by ``self.backend`` for the splats' device (what :meth:`render`
        uses when given none); the exact learned mode and the kernels without a native op
        (gabsplat, learned-paper), which only the torch path draws, refuse the native ``cpu``
        backend by name (``auto`` draws them with torch). Raises ``BackendUnavailable`` (with the reason) for
        a backend that cannot run on the splats' device."""
        if self.backend == "cpu" and self.kernel2d.decoded and self.exact:
            raise ValueError("the exact learned mode has no cpu backend; use backend torch")
        if self.backend == "cpu" and not self.kernel2d.has_native:
            raise ValueError(f"the {self.kernel} kernel has no cpu backend; use backend torch or auto")
        return backends.get(self.backend, self.xy_raw.device)

    def uses_native(self, backend: Backend | None = None) -> bool:
        """Whether :meth:`render` with ``backend`` (default: :meth:`resolve_backend`) runs a native
        op (see the module docstring)."""
        backend = self.resolve_backend() if backend is None else backend
        if not self.kernel2d.has_native or (self.kernel2d.decoded and self.exact):
            return False
        return backend.render_image_splats is not None

    def render(self, backend: Backend | None = None) -> Tensor:
        """[H, W, 3] image (unclamped sum of the splats), drawn with ``backend``'s native op when
        it has one, else by the torch path. ``backend`` default: :meth:`resolve_backend`."""
        backend = self.resolve_backend() if backend is None else backend
        means = self.means_px()
        l11, l21, l22 = self.chol_factors()
        table = self.kernel2d.table(self)
        if self.uses_native(backend):
            x0, y0, rx, ry = self._boxes(means.detach(), l11.detach(), l21.detach(), l22.detach())
            bbox = torch.stack([x0, y0, x0 + 2 * rx + 1, y0 + 2 * ry + 1], 1).to(torch.int32).contiguous()
            chol = torch.stack([l11, l21, l22], 1)
            kind, aux, extras = self.kernel2d.native(self, table)
            return backend.render_image_splats(means, chol, self.colors, extras, bbox, kind, aux,
                                               self.width, self.height)
        idx, px, py = self._pairs(means.detach(), l11.detach(), l21.detach(), l22.detach())
        # one packed gather per chunk: mean 2, L 3, colour 3, kernel extras
        packed = torch.cat([means, l11[:, None], l21[:, None], l22[:, None], self.colors, self._extras()], 1)
        out = torch.zeros(self.height * self.width, 3, dtype=means.dtype, device=means.device)
        for s in range(0, idx.numel(), CHUNK_PAIRS):
            i, x, y = idx[s:s + CHUNK_PAIRS], px[s:s + CHUNK_PAIRS], py[s:s + CHUNK_PAIRS]
            # one split, not a slice per column: each slice's backward fills a zero [P, 8 + E]
            mx, my, l11s, l21s, l22s, cols, extras = packed.index_select(0, i).split(
                [1, 1, 1, 1, 1, 3, packed.shape[1] - 8], 1)
            dx = (x.to(means.dtype) + 0.5) - mx[:, 0]
            dy = (y.to(means.dtype) + 0.5) - my[:, 0]
            u = dx / l11s[:, 0]
            v = (dy - l21s[:, 0] * u) / l22s[:, 0]  # L^-1 (x - mu), forward substitution
            uv = torch.stack([u, v], -1) * (1.0 / SUPPORT_SIGMAS)
            w = self.kernel_values(uv, i, table, extras)
            out = out.index_add(0, (y * self.width + x).long(), w[:, None] * cols)
        return out.reshape(self.height, self.width, 3)

    def describe_bytes(self) -> dict:
        """Honest storage: per-splat floats at float32 (and a byte per turn, palette index or wave
        index), the shared decoder and palette at float16. ``bytes`` is everything needed to redraw
        the image, and what :func:`splatk.image.file.save_splats2d` writes after its header;
        ``counted_bytes`` is what the budget paid for (``bytes`` less the shared part for the
        paper's kernel, whose comparison counts the primitives only)."""
        # the palette actually made (k-means makes fewer entries than asked when n < shapes)
        shapes = self.palette.shape[0] if self.palette is not None else self.shapes
        per = bytes_per_primitive(self.kernel, self.latent_dim, shapes)
        net = network_bytes(self.kernel, self.latent_dim, shapes)
        counted = per * self.n + (net if self.kernel2d.pays_shared else 0)
        return {"bytes": per * self.n + net, "primitive_bytes": per * self.n, "bytes_per_primitive": per,
                "network_bytes": net, "counted_bytes": counted}

"""The weights of a neural material: their names and shapes, stated once.

Two views of the same numbers, both from a `MaterialConfig`:

- `weight_shapes`: the weights as the model holds them, and as `training.export.build_onnx` takes
  them and `training.export.read.read_model` gives them back: the textures (``pyramid``, the flat
  atlas of every level, finest first; ``offset_texture``, one level, or with `MaterialConfig.offset_mip` its mip
  pyramid's atlas; with `MaterialConfig.base`, ``base_maps``, the base maps' atlas, finest first; with `MaterialConfig.relief`, ``relief_heights``) and each MLP's layers
  (``{mlp}.{i}.weight`` (out, in), ``{mlp}.{i}.bias`` (out,)). An MLP's first layer reads the
  texture features, then the query columns `MLP_QUERY_COLUMNS` names, in that order.
- `initializer_shapes`: the initializers the exported graph stores them in. Matrices are stored halved
  (``{mlp}.{i}.half_weight``; the graph's Gemm multiplies by 2), biases as columns (out, 1); a first
  layer is split by what it reads (``{mlp}.0.half_weight.texture``, ``.query``: a (hidden, 7) matrix
  over the whole query row, zero but for the columns it reads, the decoder's ``.light``: its
  columns on a light's wi, and a part per optional input, ``.NAME`` for each row of `config.DECODER_INPUTS`
  it reads); the offset MLP's last layer is stored with ``offset_scale`` folded in and
  its one output twice (the depth beside each of wo_x, wo_y).

Names and shapes only: no numpy, no arithmetic.
"""

from __future__ import annotations

from neumip.core import contract as C
from neumip.core.config import BASE_OUTPUTS, MaterialConfig
from neumip.core.head import outputs

PYRAMID = "pyramid"
"""The neural texture pyramid: the rows of every level, finest first (`MaterialConfig.level_starts`)."""
BASE = "base_maps"
"""The base maps' pyramid (`MaterialConfig.base`): rows of every level, finest first, `BASE_CHANNELS` wide."""
RELIEF = "relief_heights"
"""The relief's height pyramid (`MaterialConfig.relief`): rows of every level, finest first, one channel
(height in tile units, the top 0)."""
OFFSET_TEXTURE = "offset_texture"
"""The neural offset texture: one level at the finest resolution, or with `MaterialConfig.offset_mip` the rows of
every level of its mip pyramid, finest first (the coarser levels derived from the finest, `pyramid.mip_levels`)."""
ENERGY = "energy"
"""The answers' energy table (`MaterialConfig.energy_bins` B, `energy_azimuths` A): a texture of RGB gains (one gain
with `energy_luminance`), row
``((B l + b) B + e) A + a`` for level of detail l, bin b of the half vector's angle, bin e of the light's elevation and
bin a of the half vector's azimuth (A = 1 and a = 0 without that axis); 1 where the model needs none."""
DECODER = "decoder"
"""The MLP that turns texture features and directions into the answer."""
COARSE_DECODER = "coarse_decoder"
"""With `MaterialConfig.coarse_decoder`: the decoder of the coarse levels, of the decoder's shape and inputs."""
DECODERS = (DECODER, COARSE_DECODER)
"""The MLPs that read the texture features, the optional inputs and the directions."""
OFFSET_MLP = "offset_mlp"
"""The MLP that turns offset-texture features and wo into a ray depth."""

MLP_QUERY_COLUMNS = {DECODER: (C.WI_X, C.WI_Y, C.WO_X, C.WO_Y), COARSE_DECODER: (C.WI_X, C.WI_Y, C.WO_X, C.WO_Y),
                     OFFSET_MLP: (C.WO_X, C.WO_Y)}
"""The query columns each MLP's first layer reads after its texture's features."""

FIRST_LAYER_PARTS = {DECODER: ("texture", "query", "light"), COARSE_DECODER: ("texture", "query", "light"),
                     OFFSET_MLP: ("texture", "query")}
"""What each MLP's stored first layer is split into (`half_weight`); a decoder's also has a part per optional
input it reads (`MaterialConfig.decoder_inputs`), after these."""


def first_layer_parts(mlp: str, config: MaterialConfig) -> tuple[str, ...]:
    """The parts the stored first layer of `mlp` is split into."""
    extra = tuple(row.name for row in config.decoder_inputs()) if mlp in DECODERS else ()
    return FIRST_LAYER_PARTS[mlp] + extra


def texture_inputs(mlp: str, config: MaterialConfig) -> int:
    """Inputs of `mlp`'s first layer that read its texture's features."""
    return config.channels if mlp in DECODERS else config.offset_channels

DEPTH_COPIES = 2
"""Rows of the offset MLP's stored last layer: its one output, once beside each of wo_x, wo_y."""


def weight(mlp: str, layer: int) -> str:
    """Name of layer `layer`'s weights (out, in) of MLP `mlp` in `weight_shapes`."""
    return f"{mlp}.{layer}.weight"


def bias(mlp: str, layer: int) -> str:
    """Name of layer `layer`'s bias: (out,) in `weight_shapes`, (out, 1) in `initializer_shapes`."""
    return f"{mlp}.{layer}.bias"


def half_weight(mlp: str, layer: int, part: str | None = None) -> str:
    """Name of the initializer holding half of layer `layer`'s weights (``part`` of a first layer:
    "texture", "query" or "light", `FIRST_LAYER_PARTS`)."""
    return f"{mlp}.{layer}.half_weight" + (f".{part}" if part else "")


def decoder_extra_inputs(config: MaterialConfig) -> int:
    """The decoder's inputs between its texture features and its query columns (the optional ones, in order)."""
    return sum(row.width for row in config.decoder_inputs())


def mlps(config: MaterialConfig) -> dict[str, tuple[int, int]]:
    """The material's MLPs -> (inputs, outputs): texture features plus query columns in, answer out."""
    extra = decoder_extra_inputs(config)
    answers = BASE_OUTPUTS if config.base else outputs(config.head)
    found = {DECODER: (config.channels + extra + len(MLP_QUERY_COLUMNS[DECODER]), answers)}
    if config.coarse_decoder:
        found[COARSE_DECODER] = found[DECODER]
    if config.offset:
        found[OFFSET_MLP] = (config.offset_channels + len(MLP_QUERY_COLUMNS[OFFSET_MLP]), 1)
    return found


def textures(config: MaterialConfig) -> list[str]:
    """Names of the material's textures."""
    return ([PYRAMID] + ([OFFSET_TEXTURE] if config.offset else []) + ([BASE] if config.base else [])
            + ([RELIEF] if config.relief else []))


def _other_texture_shapes(config: MaterialConfig, finest_level: int = 0) -> dict[str, tuple[int, int]]:
    """The textures other than the latents: the offset texture, the base's maps, the relief's heights; a pyramid's
    (the offset's with `MaterialConfig.offset_mip`) of a model trimmed to latent level K = ``finest_level`` holds
    its levels of the same footprint on (`MaterialConfig.pyramid_finest_level`)."""
    shapes = {}
    if config.offset and config.offset_pyramid() is None:
        shapes[OFFSET_TEXTURE] = (config.resolution**2, config.offset_channels)
    for name, pyramid in ((OFFSET_TEXTURE, config.offset_pyramid()), (BASE, config.base_pyramid()),
                          (RELIEF, config.relief_pyramid())):
        if pyramid is not None:
            level = config.pyramid_finest_level(pyramid, finest_level)
            shapes[name] = (pyramid.atlas_rows() - pyramid.level_starts()[level], pyramid.channels)
    return shapes


def _widths(config: MaterialConfig, inputs: int, answers: int) -> list[int]:
    """Widths of an MLP's activations, input to output: layers + 1 values."""
    return [inputs] + [config.hidden] * (config.layers - 1) + [answers]


def energy_rows(config: MaterialConfig) -> int:
    """The energy table's rows, (L + 1) B^2 A (`ENERGY`; A = 1 without the azimuth axis), 0 without a table."""
    return (config.levels + 1) * config.energy_bins**2 * max(config.energy_azimuths, 1) if config.energy_bins else 0


def tie_normal_cells(table, config: MaterialConfig) -> None:
    """Give the energy table's cells of the first half-vector bin (the normal, where the azimuth is undefined) their
    mean over the azimuths, in place (a numpy array or a torch tensor of `energy_shape`); a fit ties them so
    (`training.model.energy.fit_energy`), and a table made otherwise must be tied for the gain to be continuous."""
    if config.energy_azimuths:
        cells = table.reshape(config.levels + 1, config.energy_bins, config.energy_bins, config.energy_azimuths, -1)
        cells[:, 0] = cells[:, 0].mean(2)[:, :, None]


def energy_shape(config: MaterialConfig) -> dict[str, tuple[int, int]]:
    """The energy table's shape by name (`ENERGY`: (`energy_rows`, `energy_channels`), every level's cells, a trimmed model's too),
    or nothing without one."""
    return {ENERGY: (energy_rows(config), energy_channels(config))} if config.energy_bins else {}


def energy_channels(config: MaterialConfig) -> int:
    """The energy table's gains a cell: 3 (RGB), or 1 with `MaterialConfig.energy_luminance`."""
    return 1 if config.energy_luminance else C.RGB_DIM


def weight_shapes(config: MaterialConfig) -> dict[str, tuple[int, ...]]:
    """Every weight of the material -> its shape, as the model holds it (textures first, then the energy table,
    then each MLP's layers in order)."""
    shapes: dict[str, tuple[int, ...]] = {PYRAMID: (config.atlas_rows(), config.channels)}
    shapes.update(_other_texture_shapes(config))
    shapes.update(energy_shape(config))
    for mlp, (inputs, answers) in mlps(config).items():
        widths = _widths(config, inputs, answers)
        for i in range(config.layers):
            shapes[weight(mlp, i)] = (widths[i + 1], widths[i])
            shapes[bias(mlp, i)] = (widths[i + 1],)
    return shapes


def offset_levels_derived(config: MaterialConfig, finest_level: int = 0) -> bool:
    """Whether the file stores the offset's mip pyramid (`MaterialConfig.offset_mip`) as its finest level alone, the
    graph deriving the others when it loads: where the model holds it whole (a trim stores the levels it keeps)."""
    mips = config.offset_pyramid()
    return mips is not None and config.pyramid_finest_level(mips, finest_level) == 0


def initializer_shapes(config: MaterialConfig, finest_level: int = 0) -> dict[str, tuple[int, ...]]:
    """Every initializer of the exported graph that holds a weight -> its shape (the graph's other
    initializers are constants of its arithmetic). ``finest_level`` K > 0: a trimmed model, whose
    pyramid holds levels K..L only. The file stores nothing it can derive: an untrimmed offset mip pyramid is its
    finest level, and the base's maps (`BASE`) hold only the map channels that vary between texels before the
    horizons, so their width is at most the one given here (`training/export/base.read_base`)."""
    starts = config.level_starts()
    rows = config.atlas_rows() - starts[finest_level]
    shapes: dict[str, tuple[int, ...]] = {PYRAMID: (rows, config.channels)}
    shapes.update(_other_texture_shapes(config, finest_level))
    if offset_levels_derived(config, finest_level):  # its finest level: the graph derives the rest
        shapes[OFFSET_TEXTURE] = (config.offset_pyramid().resolution**2, config.offset_channels)
    shapes.update(energy_shape(config))
    for mlp, (inputs, answers) in mlps(config).items():
        widths = _widths(config, inputs, DEPTH_COPIES if mlp == OFFSET_MLP else answers)
        first = {"texture": texture_inputs(mlp, config), "query": C.QUERY_DIM, "light": 2,
                 **{row.name: row.width for row in config.decoder_inputs()}}
        for part in first_layer_parts(mlp, config):
            shapes[half_weight(mlp, 0, part)] = (widths[1], first[part])
        shapes[bias(mlp, 0)] = (widths[1], 1)
        for i in range(1, config.layers):
            shapes[half_weight(mlp, i)] = (widths[i + 1], widths[i])
            shapes[bias(mlp, i)] = (widths[i + 1], 1)
    return shapes

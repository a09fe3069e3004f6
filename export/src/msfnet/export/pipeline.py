"""``run_export``: the passes of one variant, one write, verification of the written file, rename.

Order of events (see ``pipeline.export_variant`` for the public entry point); the file is
written by ``common/files.py`` like every msfnet output:
1. the target checked (``files.check_output``: not an input, writable, not existing unless
   --overwrite) before any slow work;
2. checkpoint and calibration stacks loaded (bad input fails here, still before the export);
3. the variant's passes on the in-memory model; before the first lossy pass (int8) the model
   so far is checked against PyTorch and becomes the reference (int8's quantiser works on
   files: they go to a ``files.scratch_folder`` beside the target, removed right after);
4. one write of the final bytes into ``files.write_atomic``'s temporary sibling of the target;
5. that file loaded by ONNX Runtime through the runtime's loader and compared with the
   variant's reference (unit normals required too), still under its temporary name;
6. only then one atomic rename onto the target. Any failure or interruption before that
   removes the temporary file and leaves the target as it was; one left by ``kill -9`` is
   removed by the next export to the same target.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

import torch

from msfnet.common.errors import InputError
from msfnet.common.files import check_output, write_atomic
from msfnet.common.signals import Terminated
from msfnet.common.vocabulary import opt
from msfnet.export.onnx_export import STAGED_CHECK_CHUNK, default_checks
from msfnet.export.passes import PASSES, PassContext
from msfnet.export.variants import (
    FP32_RULE,
    ExportOptions,
    ExportResult,
    Variant,
    VerificationRow,
    check_options,
    get_variant,
)
from msfnet.export.verify import (
    compare,
    file_runner,
    judge,
    proto_runner,
    rendered_cases,
    tile_cases,
    torch_runner,
)
from msfnet.model.checkpoint import load_model
from msfnet.model.network import MSFNet
from msfnet.runtime.stack import Stack

# zip (torch >= 1.6), or a pickle stream (legacy torch.save starts with a pickled magic number)
_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")
_PICKLE_PROTOCOLS = range(2, 6)


def sniff_checkpoint(path: Path) -> None:
    """Refuse a file that is neither of torch.save's two formats before torch reads it (torch's
    weights-only loader reports random bytes as 'unsupported pickled objects')."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except FileNotFoundError:
        raise InputError("checkpoint file not found", path) from None
    except IsADirectoryError:
        raise InputError("is a folder, not a PyTorch checkpoint file", path) from None
    except OSError as exc:
        raise InputError(f"cannot read the checkpoint ({exc.strerror or exc})", path) from exc
    if not head:
        raise InputError("empty file, not a PyTorch checkpoint", path)
    if head in _ZIP_MAGIC or (head[0] == 0x80 and len(head) > 1 and head[1] in _PICKLE_PROTOCOLS):
        return
    raise InputError(
        "not a PyTorch checkpoint (neither torch.save's zip format nor its legacy pickle format)",
        path,
    )


def load_network(checkpoint: Path, fp16_weights: bool) -> MSFNet:
    """The checkpoint's network (weights_only loading); for fp16 variants with its weights
    rounded to float16 and back, the reference the fp16-stored file must match exactly."""
    sniff_checkpoint(checkpoint)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # torch's pickle-protocol chatter; errors still raise
        model = load_model(checkpoint)
    if fp16_weights:
        with torch.no_grad():
            for tensor in model.state_dict().values():
                if tensor.is_floating_point():
                    tensor.copy_(tensor.half().float())
    return model


def load_stacks(calib: Sequence[str | Path | Stack]) -> list[Stack]:
    from msfnet.export.quantize import load_calibration_stacks

    paths = [c for c in calib if not isinstance(c, Stack)]
    loaded = iter(load_calibration_stacks(paths) if paths else [])
    return [c if isinstance(c, Stack) else next(loaded) for c in calib]


def run_export(
    checkpoint: Path,
    variant: Variant,
    output: Path,
    *,
    calib: Sequence[str | Path | Stack],
    options: ExportOptions,
    overwrite: bool,
    log: Callable[[str], None],
) -> ExportResult:
    calib = list(calib) if variant.needs_calibration else []
    inputs = [checkpoint, *(Path(c) for c in calib if not isinstance(c, Stack))]
    staged_chunk = STAGED_CHECK_CHUNK if variant.graph == "staged" else None
    checks = list(options.checks or default_checks(options.static))
    threads = options.threads
    check_output(output, inputs, overwrite=overwrite)
    model = load_network(checkpoint, variant.precision == "fp16-weights")
    if variant.graph == "staged" and not (model.mfe and model.mff):
        raise InputError(
            "an ablation checkpoint (msf-train --no-mfe / --no-mff): the staged "
            f"graph needs the full network; export it with {opt('plain')}",
            checkpoint,
        )
    stacks = load_stacks(calib)
    import_onnxruntime()  # the passes and the verification use it: imported once, here
    ctx = PassContext(model, variant, options, checkpoint, output, stacks)
    proto = None
    reference: bytes | None = None
    reference_rows: list[VerificationRow] = []
    for name in variant.effective_passes(options.simplify):
        step = PASSES[name]
        if step.lossy and reference is None:
            assert proto is not None, f"lossy pass {name} cannot come first"
            reference = proto.SerializeToString()
            log(f"checking the fp32 graph against PyTorch (the reference for {variant.name})")
            reference_rows = compare(
                proto_runner(reference, staged_chunk, threads),
                torch_runner(model),
                rendered_cases(checks),
            )
            judge(
                reference_rows,
                FP32_RULE,
                FP32_RULE.limit_deg,
                f"the fp32 graph (reference for {variant.name})",
                checkpoint,
            )
        log(f"pass: {name}")
        proto = step.run(proto, ctx)
    assert proto is not None
    data = proto.SerializeToString()
    del proto
    limit = options.tolerance_deg if options.tolerance_deg is not None else variant.rule.limit_deg
    rows: list[VerificationRow] = []

    def write_verified(candidate: Path) -> None:
        """The candidate is renamed onto ``output`` only if this returns."""
        write_file(candidate, data, output)
        log(f"verifying the written file ({variant.rule.describe()})")
        try:
            runner = file_runner(candidate, staged_chunk, threads)
        except InputError as exc:
            # name the output the user asked for, not the temporary file (gone by now)
            problem = exc.message.replace(str(candidate), output.name)
            raise InputError(f"the written file does not load: {problem}", output) from exc
        if variant.rule.reference == "fp32-graph":
            assert reference is not None
            o = options
            rows.extend(
                compare(
                    runner,
                    proto_runner(reference, staged_chunk, threads),
                    tile_cases(
                        stacks,
                        tile=o.calib_tile,
                        lights=o.calib_lights,
                        tiles_per_stack=o.calib_tiles_per_stack,
                        train_lights=o.train_lights,
                    ),
                )
            )
        else:
            rows.extend(compare(runner, torch_runner(model), rendered_cases(checks)))
        judge(rows, variant.rule, limit, source=checkpoint)

    write_atomic(output, write_verified, overwrite=overwrite)
    return ExportResult(
        path=output,
        variant=variant.name,
        rule=variant.rule,
        limit_deg=limit,
        rows=tuple(rows),
        reference_rows=tuple(reference_rows),
        size_bytes=len(data),
        notes=dict(ctx.notes),
    )


def import_onnxruntime() -> None:
    """Import ONNX Runtime. A Ctrl-C / SIGTERM landing inside its C extension's import
    surfaces as "ImportError: initialization failed" caused by the signal's exception: that
    exception is raised instead, so the command ends as interrupted / terminated (130 / 143,
    "nothing was written"), not as an internal error."""
    try:
        import onnxruntime  # noqa: F401
    except ImportError as exc:
        seen: set[int] = set()
        cause: BaseException | None = exc
        while cause is not None and id(cause) not in seen:
            seen.add(id(cause))
            if isinstance(cause, (KeyboardInterrupt, Terminated)):
                raise cause from None
            cause = cause.__cause__ or cause.__context__
        raise


def write_file(path: Path, data: bytes, target: Path) -> None:
    """The model's bytes (``write_atomic`` flushes them to disk before the rename); errors name
    the target, not the temporary file."""
    try:
        path.write_bytes(data)
    except OSError as exc:
        raise InputError(f"cannot write the output ({exc.strerror or exc})", target) from exc


def export_variant(
    checkpoint: str | Path,
    variant: str | Variant,
    output: str | Path,
    *,
    calib: Sequence[str | Path | Stack] | None = None,
    options: ExportOptions | None = None,
    overwrite: bool = False,
    log: Callable[[str], None] | None = None,
) -> ExportResult:
    """Export ``checkpoint`` as ``variant`` to ``output``; return how the written file verified.

    ``calib``: stack paths (or loaded Stacks) for the int8 variants (ignored by the others, so
    one call shape fits every row). Raises InputError (one
    line) for bad input, an unwritable or clashing output, or a failed verification; then
    ``output`` is untouched and no temporary file remains. ``log``: progress lines.
    """
    v = get_variant(variant)
    opts = options or ExportOptions()
    check_options(v, opts, calib)
    return run_export(
        Path(checkpoint),
        v,
        Path(output),
        calib=list(calib or []),
        options=opts,
        overwrite=overwrite,
        log=log or (lambda _msg: None),
    )


__all__ = ["export_variant", "load_network", "run_export", "sniff_checkpoint"]

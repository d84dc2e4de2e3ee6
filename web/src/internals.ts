// The format's float and integer steps, exported for the tests that check them against the Python
// codec (the radius order, the table models' decays, the inverse DCT) and the kernels against the
// TypeScript path (the ANS decoder); not part of the API.
export { baseCut, cutOf, hypot, prefix, radiusLimit } from "./layout.js";
export { AnsDecoder, ansInKernels, decayOf, decodeGroup, tableModel, bernoulliLeft1, slotsOf } from "./ans.js";
export { addIdct } from "./transform.js";
export { inflate } from "./bytes.js";
export { nativeZstd, ready } from "./zstd.js";
export { BluesteinFft, factorize, MixedFft } from "./dct.js";
export { kernels, releaseKernels, useWasm, WasmMemoryError } from "./wasm.js";
export { decodeResidual } from "./residual.js";
export { decodeMask } from "./mask.js";
export { cornerFinished, decode } from "./decode.js";
// web/bench's table of stages: the decode above (this bundle's own), timed stage by stage.
export { stageTimes } from "./stages.js";

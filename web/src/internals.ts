// The format's float and integer steps, exported for the tests that check them against the Python
// codec (the radius order, the table models' decays, the inverse DCT); not part of the API.
export { baseCut, cutOf, hypot, prefix, radiusLimit } from "./layout.js";
export { decayOf, tableModel, bernoulliLeft1, slotsOf } from "./ans.js";
export { addIdct } from "./transform.js";
export { inflate } from "./bytes.js";
export { BluesteinFft, factorize, MixedFft } from "./dct.js";
export { kernels, releaseKernels, useWasm, WasmMemoryError } from "./wasm.js";
export { cornerFinished } from "./decode.js";

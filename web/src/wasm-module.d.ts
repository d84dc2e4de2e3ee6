// The build embeds web/wasm/out/kernels.wasm in the bundle as its bytes (esbuild's binary loader).
declare module "*.wasm" {
  const bytes: Uint8Array<ArrayBuffer>;
  export default bytes;
}

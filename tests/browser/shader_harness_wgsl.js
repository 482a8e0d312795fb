// Validates a WGSL texture function with the browser's WebGPU compiler (Tint in Chromium)
// and, where it compiles, runs it on `size` x `size` points as a compute shader; returns the
// compiler's messages and the pixels (row 0 = y 0.5). Used by test_shader.py.
async ({source, name, size, origin, scale, seed}) => {
  if (!navigator.gpu) return {error: "no navigator.gpu"};
  const adapter = await navigator.gpu.requestAdapter();
  if (!adapter) return {error: "no WebGPU adapter"};
  const device = await adapter.requestDevice();
  const code = `${source}
struct Params { origin: vec3<f32>, scale: f32, seed: u32, size: u32 }
@group(0) @binding(0) var<uniform> params: Params;
@group(0) @binding(1) var<storage, read_write> result: array<vec4<f32>>;
@compute @workgroup_size(8, 8)
fn main(@builtin(global_invocation_id) id: vec3<u32>) {
  if (id.x >= params.size || id.y >= params.size) { return; }
  let p = params.origin + vec3<f32>((vec2<f32>(id.xy) + 0.5) * params.scale, 0.0);
  result[id.y * params.size + id.x] = vec4<f32>(${name}(p, params.seed), 1.0);
}`;
  const t0 = performance.now();
  const module = device.createShaderModule({code});
  const info = await module.getCompilationInfo();
  const messages = info.messages.map(m => `${m.type} ${m.lineNum}:${m.linePos} ${m.message}`);
  if (info.messages.some(m => m.type === "error")) return {messages, error: "compilation failed"};
  if (!size) return {messages, compileMs: performance.now() - t0};
  device.pushErrorScope("validation");
  const pipeline = await device.createComputePipelineAsync({layout: "auto", compute: {module, entryPoint: "main"}});
  const compileMs = performance.now() - t0;
  const uniform = device.createBuffer({size: 32, usage: GPUBufferUsage.UNIFORM | GPUBufferUsage.COPY_DST});
  const ab = new ArrayBuffer(32);
  new Float32Array(ab, 0, 4).set([origin[0], origin[1], origin[2], scale]);
  new Uint32Array(ab, 16, 2).set([seed, size]);
  device.queue.writeBuffer(uniform, 0, ab);
  const bytes = size * size * 16;
  const out = device.createBuffer({size: bytes, usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_SRC});
  const read = device.createBuffer({size: bytes, usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST});
  const group = device.createBindGroup({layout: pipeline.getBindGroupLayout(0), entries: [
    {binding: 0, resource: {buffer: uniform}}, {binding: 1, resource: {buffer: out}}]});
  const t1 = performance.now();
  const encoder = device.createCommandEncoder();
  const pass = encoder.beginComputePass();
  pass.setPipeline(pipeline); pass.setBindGroup(0, group);
  pass.dispatchWorkgroups(Math.ceil(size / 8), Math.ceil(size / 8));
  pass.end();
  encoder.copyBufferToBuffer(out, 0, read, 0, bytes);
  device.queue.submit([encoder.finish()]);
  await read.mapAsync(GPUMapMode.READ);
  const pixels = Array.from(new Float32Array(read.getMappedRange()));
  const error = await device.popErrorScope();
  return {messages, pixels, compileMs, drawMs: performance.now() - t1, error: error ? error.message : undefined};
}

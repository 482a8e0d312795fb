// Renders `size` x `size` pixels of a GLSL texture function into an RGBA32F target and
// returns the pixels as a flat array (row 0 = gl_FragCoord.y 0.5). Used by test_shader.py.
async ({source, name, size, origin, scale, seed}) => {
  const canvas = document.createElement("canvas");
  canvas.width = size; canvas.height = size;
  const gl = canvas.getContext("webgl2");
  if (!gl) return {error: "no webgl2"};
  if (!gl.getExtension("EXT_color_buffer_float")) return {error: "no float render target"};
  const vs = `#version 300 es
in vec2 a; void main() { gl_Position = vec4(a, 0.0, 1.0); }`;
  const fs = `#version 300 es
precision highp float; precision highp int;
uniform vec3 u_origin; uniform float u_scale; uniform uint u_seed;
out vec4 colour;
${source}
void main() { colour = vec4(${name}(u_origin + vec3(gl_FragCoord.xy * u_scale, 0.0), u_seed), 1.0); }`;
  const compile = (type, text) => {
    const s = gl.createShader(type); gl.shaderSource(s, text); gl.compileShader(s);
    if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
    return s;
  };
  const t0 = performance.now();
  const prog = gl.createProgram();
  try {
    gl.attachShader(prog, compile(gl.VERTEX_SHADER, vs));
    gl.attachShader(prog, compile(gl.FRAGMENT_SHADER, fs));
  } catch (e) { return {error: String(e)}; }
  gl.linkProgram(prog);
  if (!gl.getProgramParameter(prog, gl.LINK_STATUS)) return {error: gl.getProgramInfoLog(prog)};
  const compileMs = performance.now() - t0;
  const tex = gl.createTexture();
  gl.bindTexture(gl.TEXTURE_2D, tex);
  gl.texStorage2D(gl.TEXTURE_2D, 1, gl.RGBA32F, size, size);
  const fb = gl.createFramebuffer();
  gl.bindFramebuffer(gl.FRAMEBUFFER, fb);
  gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, tex, 0);
  const buf = gl.createBuffer();
  gl.bindBuffer(gl.ARRAY_BUFFER, buf);
  gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
  gl.useProgram(prog);
  const loc = gl.getAttribLocation(prog, "a");
  gl.enableVertexAttribArray(loc);
  gl.vertexAttribPointer(loc, 2, gl.FLOAT, false, 0, 0);
  gl.uniform3f(gl.getUniformLocation(prog, "u_origin"), origin[0], origin[1], origin[2]);
  gl.uniform1f(gl.getUniformLocation(prog, "u_scale"), scale);
  gl.uniform1ui(gl.getUniformLocation(prog, "u_seed"), seed);
  gl.viewport(0, 0, size, size);
  const t1 = performance.now();
  gl.drawArrays(gl.TRIANGLES, 0, 3);
  const pixels = new Float32Array(size * size * 4);
  gl.readPixels(0, 0, size, size, gl.RGBA, gl.FLOAT, pixels);
  return {pixels: Array.from(pixels), compileMs, drawMs: performance.now() - t1};
}

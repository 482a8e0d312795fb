// Live GPU view: the texture's own shader (GET /v1/textures/{id}/shader.glsl, docs/SHADER.md)
// drawn with WebGL2 on a canvas, a window onto the same world plane as the tile map at
// native zoom (one canvas pixel = one exemplar pixel). Seed, plane and offset redraw at once.
// Where WebGL2 is missing or the shader does not compile, the tile map stays the view.
// Software renderers (SwiftShader, llvmpipe) take about a minute to compile the shader and
// seconds per frame: the view says so and draws anyway only when asked (the checkbox).
import { apiUrl, fetchWithKey } from './api.js';

const VERTEX = `#version 300 es
in vec2 corner;
void main() { gl_Position = vec4(corner, 0.0, 1.0); }`;

// Pixel (i, j) of the canvas, j down, is tile-raster pixel (x0 + i, y0 + j) at native zoom:
// world (u, v) = (x0 + i + 0.5, y0 + j + 0.5) / ppu, laid on the plane as the tiles are.
const fragment = (source, name) => `#version 300 es
precision highp float; precision highp int;
uniform vec2 origin;   // raster pixel of the canvas' top-left corner
uniform float height;  // canvas height in pixels
uniform float ppu;     // pixels per world unit (the model's pixels_per_unit)
uniform float offset;  // world position on the plane's third axis
uniform int plane;     // 0: xy, 1: xz, 2: yz
uniform uint seed;
out vec4 colour;
${source}
vec3 srgb(vec3 c) {
  return mix(c * 12.92, 1.055 * pow(c, vec3(1.0 / 2.4)) - 0.055, step(vec3(0.0031308), c));
}
void main() {
  vec2 uv = (origin + vec2(gl_FragCoord.x, height - gl_FragCoord.y)) / ppu;
  vec3 p = plane == 0 ? vec3(uv, offset) : plane == 1 ? vec3(uv.x, offset, uv.y) : vec3(offset, uv);
  colour = vec4(srgb(clamp(${name}(p, seed), 0.0, 1.0)), 1.0);
}`;

const PLANES = { xy: 0, xz: 1, yz: 2 };

export class GpuView {
  /** `canvas`: the view; `status`: an element for one line of state. */
  constructor(canvas, status) {
    this.canvas = canvas;
    this.status = status;
    this.gl = canvas.getContext('webgl2', { preserveDrawingBuffer: true, antialias: false });
    this.program = null;
    this.textureId = null;
    this.params = { seed: 0, plane: 'xy', offset: 0 };
    this.origin = [0, 0];
    this.ppu = 256;
  }

  /** The renderer's name, and whether it is a software one. */
  renderer() {
    if (!this.gl) return { name: 'none', software: true };
    const info = this.gl.getExtension('WEBGL_debug_renderer_info');
    const name = String(this.gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : this.gl.RENDERER));
    return { name, software: /swiftshader|llvmpipe|software|basic render/i.test(name) };
  }

  say(text, state) {
    this.status.textContent = text;
    this.canvas.dataset.state = state;
  }

  /** Fetch and compile the texture's shader, then draw; false where the map must stay the view. */
  async show(textureId, params, { ppu = 256, origin = [0, 0] } = {}) {
    Object.assign(this.params, params);
    this.ppu = ppu;
    this.origin = origin;
    if (!this.gl) { this.say('No WebGL2 here: the tile map is the view.', 'unsupported'); return false; }
    if (textureId !== this.textureId) {
      this.say('Compiling the texture\u2019s shader\u2026', 'compiling');
      const response = await fetchWithKey(apiUrl(`textures/${textureId}/shader.glsl`));
      const source = await response.text();
      const program = this.compile(source, `texspace_${textureId.replace(/[^0-9A-Za-z_]/g, '_').replace(/_+/g, '_')}`);
      if (!program) return false;
      this.program = program;
      this.textureId = textureId;
    }
    await this.draw();
    return true;
  }

  compile(source, name) {
    const gl = this.gl;
    const shader = (type, text) => {
      const s = gl.createShader(type);
      gl.shaderSource(s, text);
      gl.compileShader(s);
      return s;
    };
    const program = gl.createProgram();
    const vs = shader(gl.VERTEX_SHADER, VERTEX);
    const fs = shader(gl.FRAGMENT_SHADER, fragment(source, name));
    gl.attachShader(program, vs);
    gl.attachShader(program, fs);
    gl.bindAttribLocation(program, 0, 'corner');
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
      const log = gl.getShaderInfoLog(fs) || gl.getProgramInfoLog(program);
      this.say(`The shader did not compile here (the tile map is the view): ${log}`, 'failed');
      return null;
    }
    const buffer = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 2, gl.FLOAT, false, 0, 0);
    return program;
  }

  /** Draw with the current parameters; resolves once the frame is done (its time in the status). */
  async update(params) {
    Object.assign(this.params, params);
    if (this.program) await this.draw();
  }

  async draw() {
    const gl = this.gl;
    const { width, height } = this.canvas;
    gl.useProgram(this.program);
    const at = (n) => gl.getUniformLocation(this.program, n);
    gl.uniform2f(at('origin'), this.origin[0], this.origin[1]);
    gl.uniform1f(at('height'), height);
    gl.uniform1f(at('ppu'), this.ppu);
    gl.uniform1f(at('offset'), Number(this.params.offset) || 0);
    gl.uniform1i(at('plane'), PLANES[this.params.plane] ?? 0);
    gl.uniform1ui(at('seed'), Number(this.params.seed) >>> 0);
    gl.viewport(0, 0, width, height);
    this.say('Drawing\u2026', 'drawing');
    await new Promise((resolve) => requestAnimationFrame(resolve));
    const started = performance.now();
    gl.drawArrays(gl.TRIANGLES, 0, 3);
    gl.readPixels(0, 0, 1, 1, gl.RGBA, gl.UNSIGNED_BYTE, new Uint8Array(4)); // waits for the frame
    const ms = performance.now() - started;
    const { name, software } = this.renderer();
    this.say(`${width}\u00d7${height} px in ${ms.toFixed(0)} ms on ${software ? 'a software renderer' : 'the GPU'} (${name}).`, 'drawn');
    this.canvas.dataset.frameMs = ms.toFixed(1);
  }
}

// three.js viewer for a baked GLB: orbit controls, soft lights, camera fitted to the model.
import * as THREE from 'three';
import { OrbitControls } from 'three/addons/controls/OrbitControls.js';
import { GLTFLoader } from 'three/addons/loaders/GLTFLoader.js';
import { fetchWithKey } from './api.js';
import { isZip, zipMemberEndingIn } from './unzip.js';

/**
 * Vertex normals averaged over every vertex at the same position, so that the UV
 * atlas's seams (where vertices are split) do not show as creases in the shading.
 */
export function smoothNormals(geometry) {
  geometry.computeVertexNormals(); // area-weighted normals per (split) vertex
  const position = geometry.attributes.position;
  const normal = geometry.attributes.normal;
  const sums = new Map(); // position key -> [nx, ny, nz]
  const keyOf = (i) => `${position.getX(i).toFixed(5)},${position.getY(i).toFixed(5)},${position.getZ(i).toFixed(5)}`;
  for (let i = 0; i < position.count; i += 1) {
    const key = keyOf(i);
    const sum = sums.get(key) || [0, 0, 0];
    sum[0] += normal.getX(i); sum[1] += normal.getY(i); sum[2] += normal.getZ(i);
    sums.set(key, sum);
  }
  for (let i = 0; i < position.count; i += 1) {
    const [x, y, z] = sums.get(keyOf(i));
    const length = Math.hypot(x, y, z) || 1;
    normal.setXYZ(i, x / length, y / length, z / length);
  }
  normal.needsUpdate = true;
}

export class MeshViewer {
  /** @param {HTMLElement} element  container; the canvas fills it */
  constructor(element) {
    this.element = element;
    // preserveDrawingBuffer lets tests (and "save image") read the canvas back.
    this.renderer = new THREE.WebGLRenderer({ antialias: true, preserveDrawingBuffer: true });
    this.renderer.setPixelRatio(Math.min(window.devicePixelRatio, 2));
    this.renderer.setClearColor(0x2b2b2e);
    element.appendChild(this.renderer.domElement);

    this.scene = new THREE.Scene();
    this.camera = new THREE.PerspectiveCamera(40, 1, 0.01, 100);
    this.camera.position.set(0, 0.6, 3);
    this.scene.add(new THREE.HemisphereLight(0xffffff, 0x444450, 2.0));
    const sun = new THREE.DirectionalLight(0xffffff, 1.5);
    sun.position.set(2, 3, 4);
    this.scene.add(sun);

    this.controls = new OrbitControls(this.camera, this.renderer.domElement);
    this.controls.enableDamping = true;
    this.controls.addEventListener('change', () => this.render());
    this.model = null;
    this.loadedUrl = null;

    new ResizeObserver(() => this.resize()).observe(element);
    this.resize();
    this._loop();
  }

  resize() {
    const { clientWidth: w, clientHeight: h } = this.element;
    if (!w || !h) return;
    this.renderer.setSize(w, h);
    this.camera.aspect = w / h;
    this.camera.updateProjectionMatrix();
    this.render();
  }

  render() {
    this.renderer.render(this.scene, this.camera);
  }

  _loop() {
    // Damping needs a few frames after the user lets go; otherwise we render on change.
    requestAnimationFrame(() => this._loop());
    if (this.controls.update()) this.render();
  }

  /**
   * Load a bake from a URL (with the API key when one is set), replace the current model
   * and frame it. The result is a GLB, or a zip holding one (a GLB bake with a height map
   * or a GPU texture): its .glb member is read out of it. Bakes embed their images, so
   * nothing else is fetched.
   */
  async load(url) {
    const response = await fetchWithKey(url);
    let bytes = await response.arrayBuffer();
    if (isZip(bytes)) bytes = await zipMemberEndingIn(bytes, '.glb');
    const gltf = await new GLTFLoader().parseAsync(bytes, '');
    if (this.model) this.scene.remove(this.model);
    this.model = gltf.scene;
    this.model.traverse((node) => {
      // GLTFLoader flat-shades meshes that come without normals; bakes are smooth surfaces.
      if (node.isMesh && node.material.flatShading) {
        smoothNormals(node.geometry);
        node.material.flatShading = false;
        node.material.needsUpdate = true;
      }
    });
    this.scene.add(this.model);
    this._frame(this.model);
    this.loadedUrl = url;
    this.element.dataset.loaded = url;
    this.element.querySelector('.viewer-hint')?.remove();
    this.render();
  }

  _frame(object) {
    const box = new THREE.Box3().setFromObject(object);
    const dims = box.getSize(new THREE.Vector3());
    const size = Math.max(dims.x, dims.y, dims.z) || 1;
    const center = box.getCenter(new THREE.Vector3());
    this.controls.target.copy(center);
    // Far enough that the largest side fills about 3/4 of the view's height.
    const distance = (0.65 * size) / Math.tan((this.camera.fov * Math.PI) / 360) + size / 2;
    this.camera.position.copy(center).add(new THREE.Vector3(0.35, 0.3, 1).normalize().multiplyScalar(distance));
    this.camera.near = size / 100;
    this.camera.far = size * 100;
    this.camera.updateProjectionMatrix();
    this.controls.update();
  }
}

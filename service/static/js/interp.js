// Interpolation panel: two texture pickers and a slider. Moving the slider creates the
// blended texture through POST /v1/textures/interpolate (debounced, cached per a/b/t) and
// shows it on the map; the strip shows a -> b at a few t values.
import { interpolate, tileUrl, apiUrl, tileJson, setImageSource } from './api.js';
import { nativeZoomOf } from './map.js';

const STRIP_STEPS = [0, 0.25, 0.5, 0.75, 1];
const DEBOUNCE_MS = 350;

export class InterpolationPanel {
  constructor({ selectA, selectB, slider, output, showButton, strip, getParams, onBlend, onError, stripPath }) {
    Object.assign(this, { selectA, selectB, slider, output, showButton, strip, getParams, onBlend, onError });
    // Optional server endpoint that evaluates per-point codes (a -> b across space).
    this.stripPath = stripPath || null;
    this.cache = new Map(); // "a|b|t" -> Promise<texture>
    this.timer = null;
    slider.addEventListener('input', () => {
      output.value = Number(slider.value).toFixed(2);
      this._debounced();
    });
    // The strip creates blended textures on the server, so it is drawn only once the
    // user works with this panel, not on every page load.
    this.active = false;
    for (const select of [selectA, selectB]) {
      select.addEventListener('change', () => { this.active = true; this.refresh(); });
    }
    showButton.addEventListener('click', () => this.showBlend());
  }

  /** Fill both pickers from the texture list, keeping the current choices. */
  setTextures(textures) {
    for (const [index, select] of [this.selectA, this.selectB].entries()) {
      const previous = select.value;
      select.replaceChildren(...textures.map((t) => new Option(t.name || t.id, t.id)));
      if (textures.some((t) => t.id === previous)) select.value = previous;
      else if (textures.length > index) select.value = textures[index].id;
    }
  }

  _ready() {
    return this.selectA.value && this.selectB.value;
  }

  _blend(t) {
    // The ends are the picked textures themselves: nothing to create.
    for (const [end, select] of [[0, this.selectA], [1, this.selectB]]) {
      if (t === end) return Promise.resolve({ id: select.value, name: select.selectedOptions[0].text });
    }
    const key = `${this.selectA.value}|${this.selectB.value}|${t.toFixed(2)}`;
    if (!this.cache.has(key)) {
      const pending = interpolate(this.selectA.value, this.selectB.value, t);
      pending.catch(() => this.cache.delete(key));
      this.cache.set(key, pending);
    }
    return this.cache.get(key);
  }

  _debounced() {
    clearTimeout(this.timer);
    this.timer = setTimeout(() => this.showBlend(), DEBOUNCE_MS);
  }

  async showBlend() {
    if (!this._ready()) return;
    if (!this.active) { this.active = true; this.refresh(); }
    try {
      const texture = await this._blend(Number(this.slider.value));
      this.onBlend(texture);
    } catch (error) {
      this.onError(error);
    }
  }

  /** Redraw the a -> b strip for the current pair and seed. */
  async refresh() {
    if (!this._ready() || !this.active) return;
    const { seed } = this.getParams();
    const [a, b] = [this.selectA.value, this.selectB.value];
    if (this.stripPath) {
      const img = document.createElement('img');
      img.className = 'strip-wide';
      img.alt = 'Continuous blend from texture A to texture B';
      setImageSource(img, apiUrl(this.stripPath, { a, b, seed }));
      this.strip.replaceChildren(img);
      return;
    }
    // No per-point-code endpoint: one tile of a separately blended texture per t.
    const figures = STRIP_STEPS.map((t) => {
      const figure = document.createElement('figure');
      const img = document.createElement('img');
      img.alt = `Blend at t = ${t}`;
      figure.append(img, Object.assign(document.createElement('figcaption'), { textContent: `t = ${t}` }));
      this._blend(t)
        .then(async (texture) => {
          const zoom = nativeZoomOf(await tileJson(texture.id));
          setImageSource(img, tileUrl(texture.id, zoom, 0, 0, { ...this.getParams(), size: 128 }));
        })
        .catch((error) => this.onError(error));
      return figure;
    });
    this.strip.replaceChildren(...figures);
  }
}

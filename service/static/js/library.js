// Texture library pieces: list items with thumbnails, and the upload drop zone.
import * as api from './api.js';
import { nativeZoomOf } from './map.js';

/** Exemplar as thumbnail; textures without one (blends) show a tile of themselves. */
function showThumbnail(img, texture) {
  const showTile = async () => {
    try {
      const zoom = nativeZoomOf(await api.tileJson(texture.id));
      api.setImageSource(img, api.tileUrl(texture.id, zoom, 0, 0, { seed: 0, plane: 'xy', offset: 0, size: 64 }));
    } catch { /* leave the empty thumbnail */ }
  };
  if (texture.source === 'interpolate') { showTile(); return; }
  img.addEventListener('error', showTile, { once: true });
  api.setImageSource(img, api.exemplarUrl(texture.id));
}

// With an API key thumbnails are fetched by script, so loading="lazy" no longer defers
// them: fetch each when it scrolls into view (every request counts against the key's
// rate limit).
const lazyThumbnails = 'IntersectionObserver' in window ? new IntersectionObserver((entries, observer) => {
  for (const entry of entries) {
    if (!entry.isIntersecting) continue;
    observer.unobserve(entry.target);
    entry.target._showThumbnail();
  }
}, { rootMargin: '200px' }) : null;

/** The name a texture is shown (and searched) by. */
export function textureName(texture) {
  return texture.name || texture.id;
}

/** Does `texture` match the library's search text (name or id, any case)? */
export function matches(texture, query) {
  const q = query.trim().toLowerCase();
  return !q || textureName(texture).toLowerCase().includes(q) || texture.id.startsWith(q);
}

/**
 * <li> with a toggle button (thumbnail, name, code) that selects the texture, and a
 * delete button (onDelete(texture)) when `onDelete` is given.
 */
export function textureItem(texture, { pressed, onSelect, onDelete = null }) {
  const item = document.createElement('li');
  const button = document.createElement('button');
  button.type = 'button';
  button.className = 'pick';
  button.dataset.id = texture.id;
  button.setAttribute('aria-pressed', String(pressed));
  const img = document.createElement('img');
  img.alt = '';
  img.loading = 'lazy';
  if (api.hasApiKey() && lazyThumbnails) {
    img._showThumbnail = () => showThumbnail(img, texture);
    lazyThumbnails.observe(img);
  } else {
    showThumbnail(img, texture);
  }
  const meta = document.createElement('span');
  meta.className = 'meta';
  const name = document.createElement('span');
  name.textContent = textureName(texture);
  const code = document.createElement('small');
  code.textContent = Array.isArray(texture.code) ? texture.code.map((c) => c.toFixed(2)).join(' ') : '';
  meta.append(name, code);
  button.append(img, meta);
  button.addEventListener('click', () => onSelect(texture));
  item.append(button);
  if (onDelete) {
    const remove = document.createElement('button');
    remove.type = 'button';
    remove.className = 'delete';
    remove.textContent = '\u00d7';
    remove.title = `Delete ${textureName(texture)}`;
    remove.setAttribute('aria-label', `Delete ${textureName(texture)}`);
    remove.addEventListener('click', () => onDelete(texture));
    item.append(remove);
  }
  return item;
}

/**
 * A drop zone that is also the (keyboard-usable) label of a file input: dropped or
 * chosen files go to onFiles([file, ...]) (one or several).
 */
export function wireDropZone(zone, input, onFiles) {
  input.addEventListener('change', () => {
    const files = [...input.files];
    input.value = '';
    if (files.length) onFiles(files);
  });
  zone.addEventListener('keydown', (event) => {
    if (event.key === 'Enter' || event.key === ' ') { event.preventDefault(); input.click(); }
  });
  for (const type of ['dragenter', 'dragover']) {
    zone.addEventListener(type, (event) => { event.preventDefault(); zone.classList.add('over'); });
  }
  for (const type of ['dragleave', 'drop']) {
    zone.addEventListener(type, () => zone.classList.remove('over'));
  }
  zone.addEventListener('drop', (event) => {
    event.preventDefault();
    if (event.dataTransfer.files.length) onFiles([...event.dataTransfer.files]);
  });
}

// The infinite texture plane as a Leaflet map. L.CRS.Simple maps one map pixel at
// zoom 0 to one unit, and Leaflet's tile (z, x, y) covers pixels
// [x*256, (x+1)*256) x [y*256, (y+1)*256) with y growing down: exactly the API's XYZ
// tile convention, so Leaflet's zoom is the API's zoom and no coordinate maths is needed.
// noWrap and no bounds: x and y run over all integers, negatives included.
/* global L */
import { fetchBlob, fetchWithKey, hasApiKey, tileJson, tileTemplate } from './api.js';

const TILE_SIZE = 256;

/**
 * A TileLayer that fetches each tile with the API key header (an <img src> cannot send
 * one) and shows it from a blob: URL; the URL is revoked and an unfinished fetch aborted
 * when Leaflet unloads the tile. Used only while a key is set; otherwise the map is a
 * plain L.TileLayer, exactly as without keys.
 */
export const KeyedTileLayer = L.TileLayer.extend({
  initialize(url, options) {
    L.TileLayer.prototype.initialize.call(this, url, options);
    this.on('tileunload tileabort', ({ tile }) => KeyedTileLayer.release(tile));
  },

  createTile(coords, done) {
    const tile = document.createElement('img');
    L.DomEvent.on(tile, 'load', L.Util.bind(this._tileOnLoad, this, done, tile));
    L.DomEvent.on(tile, 'error', L.Util.bind(this._tileOnError, this, done, tile));
    tile.alt = '';
    tile.setAttribute('role', 'presentation');
    const url = this.getTileUrl(coords);
    tile.dataset.src = url; // the API URL (src is a blob: URL)
    const controller = new AbortController();
    tile._texspaceAbort = controller;
    fetchBlob(url, { signal: controller.signal })
      .then((blob) => {
        if (controller.signal.aborted) return;
        tile._texspaceBlobUrl = URL.createObjectURL(blob);
        tile.src = tile._texspaceBlobUrl; // -> load -> done(null, tile)
      })
      .catch((error) => { if (!controller.signal.aborted) done(error, tile); });
    return tile;
  },

  statics: {
    release(tile) {
      tile._texspaceAbort?.abort();
      if (tile._texspaceBlobUrl) URL.revokeObjectURL(tile._texspaceBlobUrl);
      tile._texspaceBlobUrl = null;
    },
  },
});

// A busy server answers cold tiles with 503 + Retry-After (back-pressure): an <img> cannot
// read the status, so a failed tile is asked for again a few times, a little later each
// time, under a URL of its own (`retry=n`, ignored by the server) so the browser fetches it.
const TILE_RETRIES = 6;
const TILE_RETRY_MS = 1500;
const TILE_RETRY_MAX_MS = 8000;

/** L.TileLayer whose failed tiles are retried (TILE_RETRIES, about 30 s in all) before Leaflet gives up. */
export const RetryingTileLayer = L.TileLayer.extend({
  _tileOnError(done, tile, error) {
    const tries = tile._texspaceTries || 0;
    if (tries >= TILE_RETRIES || !this._map) {
      L.TileLayer.prototype._tileOnError.call(this, done, tile, error);
      return;
    }
    tile._texspaceTries = tries + 1;
    const url = new URL(tile.src);
    setTimeout(() => {
      if (!tile.isConnected || !this._map) return; // unloaded meanwhile (panned away, new texture)
      url.searchParams.set('retry', String(tries + 1));
      tile.src = url.toString();
    }, Math.min(TILE_RETRY_MS * (tries + 1), TILE_RETRY_MAX_MS) * (0.75 + 0.5 * Math.random()));
  },
});

// Progressive zoom-out: a zoomed-out tile the server does not hold yet comes first as a
// preview (header X-Texspace-Tile: preview, no-cache) while the exact tile renders behind
// it. The map asks again (revalidating: 304 while it is still a preview) until the answer
// is the exact tile, and shows that from a blob: URL (revoked when the tile unloads).
const PREVIEW_POLL_MS = 1500;
const PREVIEW_POLLS = 40; // about a minute: the exact tiles of a busy view render one by one

async function sharpenPreview(tile, isLive) {
  const url = tile.dataset.src || tile.src; // the API URL (a keyed layer shows a blob: URL)
  for (let poll = 0; poll < PREVIEW_POLLS; poll += 1) {
    await new Promise((resolve) => setTimeout(resolve, PREVIEW_POLL_MS));
    if (!isLive()) return;
    let response;
    try {
      response = await fetchWithKey(url, { cache: 'no-cache' });
    } catch {
      continue; // busy or briefly unreachable: the preview stays, try again later
    }
    if (response.headers.get('X-Texspace-Tile') === 'preview') continue;
    const blobUrl = URL.createObjectURL(await response.blob());
    if (!isLive()) { URL.revokeObjectURL(blobUrl); return; }
    if (tile._texspaceBlobUrl) URL.revokeObjectURL(tile._texspaceBlobUrl);
    tile._texspaceBlobUrl = blobUrl;
    tile.dataset.src = url;
    tile._texspaceExact = true;
    tile.src = blobUrl;
    return;
  }
}

// worker/tiles.py NATIVE_ZOOM: used while the TileJSON does not say it (as `center[2]`).
const DEFAULT_NATIVE_ZOOM = 6;

/** Read the native zoom (one tile pixel = one exemplar pixel) from a TileJSON document. */
export function nativeZoomOf(tj) {
  for (const key of ['native_zoom', 'nativeZoom', 'native_zoom_level', 'texspace:native_zoom']) {
    if (Number.isInteger(tj[key])) return tj[key];
  }
  if (tj.texspace && Number.isInteger(tj.texspace.native_zoom)) return tj.texspace.native_zoom;
  if (Array.isArray(tj.center) && Number.isInteger(tj.center[2])) return tj.center[2];
  return DEFAULT_NATIVE_ZOOM;
}

export class TextureMap {
  /** @param {HTMLElement} element  container of the map */
  constructor(element, { onZoom, onTileError } = {}) {
    this.map = L.map(element, {
      crs: L.CRS.Simple,
      center: [0, 0],
      zoom: 0,
      minZoom: -4,
      maxZoom: 6,
      zoomSnap: 1,
      attributionControl: false,
      fadeAnimation: false, // tiles appear at full strength: what you see is the texture
      keyboard: true,
    });
    this.layer = null;
    this.textureId = null;
    this.params = { seed: 0, plane: 'xy', offset: 0 };
    this.nativeZoom = 0;
    this.tilesLoaded = 0;
    this.tilesFailed = 0;
    this.onZoom = onZoom || (() => {});
    this.onTileError = onTileError || (() => {});
    this.map.on('zoomend', () => this.onZoom(this.map.getZoom(), this.nativeZoom));
  }

  /**
   * Show a texture; the first one opens at `view` ({x, y, z}: centre in zoom-0 pixels, y
   * down) or at the origin at native zoom; later ones keep the current view.
   */
  async show(textureId, params = {}, view = null) {
    Object.assign(this.params, params);
    const firstTime = this.textureId === null;
    const tj = await tileJson(textureId, { seed: this.params.seed });
    this.textureId = textureId;
    this.nativeZoom = nativeZoomOf(tj);
    const minZoom = Number.isInteger(tj.minzoom) ? tj.minzoom : this.nativeZoom - 4;
    const maxZoom = Number.isInteger(tj.maxzoom) ? tj.maxzoom : this.nativeZoom + 2;
    // Jump to native zoom before any tile layer exists, so no out-of-range tiles are asked for.
    if (firstTime) {
      const zoom = Math.min(Math.max(view?.z ?? this.nativeZoom, minZoom), maxZoom + 2);
      this.map.setView([-(view?.y ?? 0), view?.x ?? 0], zoom, { animate: false });
    }
    this.map.setMinZoom(minZoom);
    // Allow two extra zoom levels past the finest tiles: Leaflet upscales them.
    this.map.setMaxZoom(maxZoom + 2);
    if (this.layer) this.layer.remove();
    const TileLayer = hasApiKey() ? KeyedTileLayer : RetryingTileLayer;
    this.layer = new TileLayer(this._template(), {
      tileSize: TILE_SIZE,
      noWrap: true,
      minZoom,
      maxZoom: maxZoom + 2,
      minNativeZoom: minZoom,
      maxNativeZoom: maxZoom,
      keepBuffer: 1,
      className: 'texture-tiles',
    });
    const layer = this.layer;
    this.layer.on('tileload', ({ tile, coords }) => {
      this.tilesLoaded += 1;
      if (coords.z < this.nativeZoom && !tile._texspaceExact && !tile._texspacePolling) {
        tile._texspacePolling = true;
        sharpenPreview(tile, () => tile.isConnected && this.layer === layer);
      }
    });
    this.layer.on('tileunload', ({ tile }) => KeyedTileLayer.release(tile)); // sharpened tiles' blob: URLs
    this.layer.on('tileerror', ({ error }) => { this.tilesFailed += 1; this.onTileError(error); });
    this.layer.addTo(this.map);
    this.onZoom(this.map.getZoom(), this.nativeZoom);
  }

  /** Take the texture off the map (e.g. when the API key changes). */
  clear() {
    if (this.layer) this.layer.remove();
    this.layer = null;
    this.textureId = null;
  }

  /** Change seed / plane / offset of the texture on show (re-requests tiles). */
  update(params) {
    Object.assign(this.params, params);
    if (this.layer) this.layer.setUrl(this._template());
  }

  /** Centre (zoom-0 pixels, y down) and zoom of the current view. */
  view() {
    const { lat, lng } = this.map.getCenter();
    return { x: Math.round(lng * 100) / 100, y: Math.round(-lat * 100) / 100, z: this.map.getZoom() };
  }

  goNative() {
    this.map.setZoom(this.nativeZoom);
  }

  _template() {
    return tileTemplate(this.textureId, { ...this.params, size: TILE_SIZE });
  }
}

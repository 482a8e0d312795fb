// Thin client for the texspace REST API (see openapi.yaml). Every function returns
// parsed JSON or throws an ApiError carrying the RFC 9457 problem's title/detail.
//
// API keys: a server with TEXSPACE_API_KEYS_ENABLED answers /v1/textures... and
// /v1/jobs... with 401 without an X-API-Key header. The page learns that from the 401 of
// its first calls (no extra request), asks for a key, keeps it in localStorage and sends
// it on every /v1 fetch. Requests the browser makes on its own (<img>, EventSource,
// <a download>) cannot carry a header, so while a key is set they go through fetch
// instead: fetchBlob / setImageSource / downloadWithKey here, streamEvents for job
// progress, a fetching tile layer in map.js. Without a key nothing changes. The key is
// never put in a URL (URLs end up in logs and history).

const BASE = new URL('v1/', document.baseURI);
const KEY_STORAGE = 'texspace.apiKey';
const KEY_HEADER = 'X-API-Key';

function readStoredKey() {
  try { return window.localStorage.getItem(KEY_STORAGE) || ''; } catch { return ''; }
}

let apiKey = readStoredKey();
let onUnauthorized = () => {};

/** The API key in use ('' when none). */
export function getApiKey() {
  return apiKey;
}

/** True while a key is set: header-less requests then go through fetch. */
export function hasApiKey() {
  return apiKey !== '';
}

/** Use and remember (localStorage) a key; '' forgets it. */
export function setApiKey(key) {
  apiKey = (key || '').trim();
  try {
    if (apiKey) window.localStorage.setItem(KEY_STORAGE, apiKey);
    else window.localStorage.removeItem(KEY_STORAGE);
  } catch { /* storage disabled: the key lasts for this page only */ }
}

/** Headers that authenticate a request: `{X-API-Key}` with a key, else `{}`. */
export function authHeaders() {
  return apiKey ? { [KEY_HEADER]: apiKey } : {};
}

/** `callback(error)` on every 401 from the API (no key, or a wrong / revoked one). */
export function setUnauthorizedHandler(callback) {
  onUnauthorized = callback;
}

function withKey(options = {}) {
  return apiKey ? { ...options, headers: { ...(options.headers || {}), ...authHeaders() } } : options;
}

/** Absolute URL of an API path such as `textures/abc/exemplar`. */
export function apiUrl(path, params = {}) {
  const url = new URL(path.replace(/^\/?(v1\/)?/, ''), BASE);
  for (const [key, value] of Object.entries(params)) {
    if (value !== undefined && value !== null && value !== '') url.searchParams.set(key, value);
  }
  return url.toString();
}

export class ApiError extends Error {
  constructor(status, problem) {
    super(problem.detail || problem.title || `HTTP ${status}`);
    this.status = status;
    this.problem = problem;
  }
}

function failure(status, body) {
  const error = new ApiError(status, typeof body === 'object' && body ? body : { detail: body });
  if (status === 401) onUnauthorized(error);
  return error;
}

/** The ApiError for a response that is not ok (reads its problem document). */
async function problemOf(response) {
  const type = response.headers.get('content-type') || '';
  let body;
  try { body = type.includes('json') ? await response.json() : await response.text(); } catch { body = ''; }
  const error = failure(response.status, body || `HTTP ${response.status}`);
  error.retryAfter = response.headers.get('retry-after');
  return error;
}

async function request(path, options = {}) {
  const response = await fetch(path.startsWith('http') ? path : apiUrl(path), withKey(options));
  const type = response.headers.get('content-type') || '';
  const body = type.includes('json') ? await response.json() : await response.text();
  if (!response.ok) throw failure(response.status, body);
  return { body, response };
}

const RATE_LIMIT_RETRIES = 3;
const MAX_RETRY_WAIT_S = 10;

/**
 * GET an API URL with the key; the ok Response, else an ApiError. A 429 (the per-key
 * rate limit: a map full of tiles can exceed its burst) is retried after Retry-After.
 */
export async function fetchWithKey(url, options = {}) {
  for (let attempt = 0; ; attempt += 1) {
    const response = await fetch(url, withKey(options));
    if (response.ok) return response;
    const error = await problemOf(response);
    if (response.status !== 429 || attempt >= RATE_LIMIT_RETRIES) throw error;
    const wait = Math.min(Number(error.retryAfter) || 1, MAX_RETRY_WAIT_S);
    await new Promise((resolve) => setTimeout(resolve, wait * 1000));
    if (options.signal?.aborted) throw new DOMException('aborted', 'AbortError');
  }
}

/** GET an API URL with the key as a Blob. */
export async function fetchBlob(url, options = {}) {
  return (await fetchWithKey(url, options)).blob();
}

/**
 * Show an API image in an <img>. Without a key: `img.src = url`, as always. With one:
 * fetched with the header and shown from a blob: URL (revoked once decoded); a failure
 * fires the img's `error` event like a failed src would. `img.dataset.src` keeps the
 * API URL.
 */
export async function setImageSource(img, url) {
  img._texspaceRetryOff?.();
  if (!apiKey) {
    retryRefusedTile(img, url);
    img.src = url;
    return;
  }
  img.dataset.src = url;
  let objectUrl;
  try {
    objectUrl = URL.createObjectURL(await fetchBlob(url));
  } catch {
    if (img.dataset.src === url) img.dispatchEvent(new Event('error'));
    return;
  }
  if (img.dataset.src !== url) { URL.revokeObjectURL(objectUrl); return; } // superseded meanwhile
  const release = () => URL.revokeObjectURL(objectUrl);
  img.addEventListener('load', release, { once: true });
  img.addEventListener('error', release, { once: true });
  img.src = objectUrl;
}

// A busy server refuses cold tiles with 503 + Retry-After (back-pressure); an <img> cannot
// read the status, so a tile image that failed is asked for again a few times, later each
// time, under a URL of its own (`retry=n`, ignored by the server). map.js does the same.
const TILE_IMAGE_RETRIES = 6;
const TILE_IMAGE_RETRY_MS = 1500;

function retryRefusedTile(img, url) {
  if (!url.includes('/tiles/')) return;
  let tries = 0;
  let timer = null;
  const onError = () => {
    if (tries >= TILE_IMAGE_RETRIES) { off(); return; }
    tries += 1;
    timer = setTimeout(() => {
      const next = new URL(url);
      next.searchParams.set('retry', String(tries));
      img.src = next.toString();
    }, Math.min(TILE_IMAGE_RETRY_MS * tries, 8000));
  };
  const off = () => {
    clearTimeout(timer);
    img.removeEventListener('error', onError);
    img.removeEventListener('load', off);
  };
  img.addEventListener('error', onError);
  img.addEventListener('load', off);
  img._texspaceRetryOff = off;
}

/** The file name in a Content-Disposition header, if any: RFC 6266's UTF-8 filename*
 * (a non-ASCII name) before the plain ASCII filename. */
function dispositionName(header) {
  const star = /filename\*=UTF-8''([^;\s]+)/i.exec(header || '');
  if (star) {
    try { return decodeURIComponent(star[1]); } catch { /* fall back to the plain name */ }
  }
  const plain = /filename="?([^";]+)"?/i.exec(header || '');
  return plain ? plain[1] : '';
}

/** Download an API resource with the key: fetch, then save the blob under its own name. */
export async function downloadWithKey(url, fallbackName = 'download') {
  const response = await fetchWithKey(url);
  const name = dispositionName(response.headers.get('content-disposition')) || fallbackName;
  const objectUrl = URL.createObjectURL(await response.blob());
  const link = Object.assign(document.createElement('a'), { href: objectUrl, download: name });
  link.hidden = true;
  document.body.append(link);
  link.click();
  link.remove();
  // The download has its own copy once started; keep the URL a while for slow starts.
  setTimeout(() => URL.revokeObjectURL(objectUrl), 60_000);
}

/**
 * Read a server-sent event stream with fetch (so the key can go in a header, which
 * EventSource cannot send). Calls onEvent({type, data, id}) per event; resolves when the
 * server ends the stream; rejects on HTTP errors (ApiError) and network errors, and
 * with an AbortError when `signal` aborts.
 */
export async function streamEvents(url, onEvent, { signal } = {}) {
  const response = await fetchWithKey(url, { headers: { accept: 'text/event-stream' }, cache: 'no-store', signal });
  const reader = response.body.pipeThrough(new TextDecoderStream()).getReader();
  let buffer = '';
  let event = { type: '', data: [], id: '' };
  const line = (text) => {
    if (text === '') {
      if (event.data.length) onEvent({ type: event.type || 'message', data: event.data.join('\n'), id: event.id });
      event = { type: '', data: [], id: event.id };
      return;
    }
    if (text.startsWith(':')) return; // comment (keep-alive)
    const colon = text.indexOf(':');
    const field = colon < 0 ? text : text.slice(0, colon);
    const value = colon < 0 ? '' : text.slice(colon + 1).replace(/^ /, '');
    if (field === 'event') event.type = value;
    else if (field === 'data') event.data.push(value);
    else if (field === 'id') event.id = value;
  };
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += value;
    // Lines end in \n, \r\n or \r; a trailing \r may be the first half of a \r\n.
    let match;
    while ((match = /\r\n|\n|\r(?!$)/.exec(buffer))) {
      line(buffer.slice(0, match.index));
      buffer = buffer.slice(match.index + match[0].length);
    }
  }
}

/** Page of textures: `{items, next_cursor}` (also accepts a plain list). */
export async function listTextures(cursor, limit = 50) {
  const { body } = await request(apiUrl('textures', { cursor, limit }));
  if (Array.isArray(body)) return { items: body, next_cursor: null };
  return {
    items: body.items || body.data || body.textures || [],
    next_cursor: body.next_cursor || body.next || null,
  };
}

export async function uploadTexture(file, name, lighting = 'as-is', widthM = null) {
  const form = new FormData();
  form.append('image', file);
  if (name) form.append('name', name);
  form.append('lighting', lighting);
  if (widthM) form.append('width_m', widthM);
  return (await request('textures', { method: 'POST', body: form })).body;
}

export async function getTexture(id) {
  return (await request(`textures/${id}`)).body;
}

export async function interpolate(a, b, t) {
  const init = { method: 'POST', headers: { 'content-type': 'application/json' }, body: JSON.stringify({ a, b, t }) };
  return (await request('textures/interpolate', init)).body;
}

export async function tileJson(id, params) {
  return (await request(apiUrl(`textures/${id}/tilejson.json`, params))).body;
}

export function exemplarUrl(id) {
  return apiUrl(`textures/${id}/exemplar`);
}

/**
 * URL template for Leaflet: {z}/{x}/{y} are filled in by the tile layer. `v` (ignored by
 * the server) names what the tiles come from, so a refined texture's tiles get new URLs
 * and no cached image of its encoder tiles is shown for them (see tileVersion).
 */
export function tileTemplate(id, { seed, plane, offset, size = 256, v }) {
  const query = new URLSearchParams({ seed, size, plane, offset });
  if (v) query.set('v', v);
  return apiUrl(`textures/${id}/tiles/`) + `{z}/{x}/{y}.png?${query}`;
}

/**
 * The `v` of a texture's tile URLs: what it serves once that is not its encoder's code,
 * 'interim' (its refinement's first state) or 'fitted', else none.
 */
export function tileVersion(texture) {
  return texture?.sampler === 'fitted' || texture?.sampler === 'interim' ? texture.sampler : undefined;
}

export function tileUrl(id, z, x, y, params) {
  return tileTemplate(id, params).replace('{z}', z).replace('{x}', x).replace('{y}', y);
}

/** Submit a job; returns the job JSON (with `id`) and the Location to poll. */
async function submitJob(path, init) {
  const { body, response } = await request(path, { method: 'POST', ...init });
  const location = response.headers.get('location');
  const job = typeof body === 'object' ? body : {};
  const id = job.id || (location ? location.split('/').filter(Boolean).pop() : null);
  return { ...job, id };
}

// The page's jobs wait for a texture's refinement while it runs (after_refinement: the
// server holds them until the refined sampler is served; it ignores the flag otherwise):
// an export or bake made while an upload is refined should look like the refined tiles.
const AFTER_REFINEMENT = true;

export function startBake(textureId, meshFile, { resolution, seed, scale, unitM, format, projection }) {
  const form = new FormData();
  form.append('mesh', meshFile, meshFile.name);
  const fields = { resolution, seed, scale, unit_m: unitM, format, projection, after_refinement: AFTER_REFINEMENT };
  for (const [key, value] of Object.entries(fields)) {
    if (value !== undefined && value !== null) form.append(key, value);
  }
  return submitJob(`textures/${textureId}/bakes`, { body: form });
}

export function startVolume(textureId, params) {
  return submitJob(`textures/${textureId}/volumes`, {
    headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ after_refinement: AFTER_REFINEMENT, ...params }),
  });
}

/** A region of the plane (RegionIn in service/schemas.py); `tileable: true` makes a square
 * image at zoom 6 that repeats without a seam. */
export function startRegion(textureId, params) {
  return submitJob(`textures/${textureId}/regions`, {
    headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ after_refinement: AFTER_REFINEMENT, ...params }),
  });
}

/** A fit (the train extra on the workers): a new texture with its own fitted sampler
 * (`output_texture_id` of the succeeded job). `seconds`: the optimisation budget. */
export function startFit(textureId, { seconds, grain = "auto", lattice = "auto" }) {
  return submitJob(`textures/${textureId}/fit`, {
    headers: { 'content-type': 'application/json' },
    body: JSON.stringify({ seconds, grain, lattice }),
  });
}

/** Delete a texture with its jobs and their files (204). */
export async function deleteTexture(id) {
  await request(`textures/${id}`, { method: 'DELETE' });
}

export async function cancelJob(id) {
  return (await request(`jobs/${id}/cancel`, { method: 'POST' })).body;
}

let limits = null;

/**
 * The server's limits (GET /v1/limits: tile sizes and planes, volume and bake resolutions,
 * a fit's default and longest budget, ...), fetched once: the page reads its numbers here
 * instead of copying them. A failed fetch is asked again next time.
 */
export function getLimits() {
  limits ||= request('limits').then(({ body }) => body, (error) => { limits = null; throw error; });
  return limits;
}

/** `{items: [{version, manifest, ...}], default}` */
export async function listModels() {
  return (await request('models')).body;
}

/** Paths of the running app's OpenAPI document (to find optional endpoints). */
export async function apiPaths() {
  const response = await fetch(new URL('openapi.json', document.baseURI));
  return response.ok ? Object.keys((await response.json()).paths || {}) : [];
}

/** Newest jobs first: `{items, next_cursor}`. */
export async function listJobs(limit = 10, textureId) {
  return (await request(apiUrl('jobs', { limit, texture_id: textureId }))).body;
}

export async function getJob(id) {
  return (await request(`jobs/${id}`)).body;
}

export function jobEventsUrl(id) {
  return apiUrl(`jobs/${id}/events`);
}

export function jobResultUrl(id) {
  return apiUrl(`jobs/${id}/result`);
}

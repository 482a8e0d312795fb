// Thin client for the texspace REST API (see openapi.yaml). Every function returns
// parsed JSON or throws an ApiError carrying the RFC 9457 problem's title/detail.

const BASE = new URL('v1/', document.baseURI);

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

async function request(path, options = {}) {
  const response = await fetch(path.startsWith('http') ? path : apiUrl(path), options);
  const type = response.headers.get('content-type') || '';
  const body = type.includes('json') ? await response.json() : await response.text();
  if (!response.ok) {
    throw new ApiError(response.status, typeof body === 'object' ? body : { detail: body });
  }
  return { body, response };
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

export async function uploadTexture(file, name) {
  const form = new FormData();
  form.append('image', file);
  if (name) form.append('name', name);
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

/** URL template for Leaflet: {z}/{x}/{y} are filled in by the tile layer. */
export function tileTemplate(id, { seed, plane, offset, size = 256 }) {
  const query = new URLSearchParams({ seed, size, plane, offset }).toString();
  return apiUrl(`textures/${id}/tiles/`) + `{z}/{x}/{y}.png?${query}`;
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

export function startBake(textureId, meshFile, { resolution, seed, scale, format }) {
  const form = new FormData();
  form.append('mesh', meshFile, meshFile.name);
  for (const [key, value] of Object.entries({ resolution, seed, scale, format })) {
    if (value !== undefined && value !== null) form.append(key, value);
  }
  return submitJob(`textures/${textureId}/bakes`, { body: form });
}

export function startVolume(textureId, params) {
  return submitJob(`textures/${textureId}/volumes`, {
    headers: { 'content-type': 'application/json' },
    body: JSON.stringify(params),
  });
}

export async function cancelJob(id) {
  return (await request(`jobs/${id}/cancel`, { method: 'POST' })).body;
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

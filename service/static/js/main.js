// Page wiring: texture library + upload, the map and its controls, interpolation, 3D jobs.
import * as api from './api.js';
import { TextureMap } from './map.js';
import { matches, textureItem, textureName, wireDropZone } from './library.js';
import { InterpolationPanel } from './interp.js';
import { JobList, TERMINAL, follow, fraction } from './jobs.js';
import { sphereObjFile } from './sphere.js';
import { readView, writeView } from './permalink.js';
import { GpuView } from './gpuview.js';

const $ = (id) => document.getElementById(id);

const state = {
  models: null,     // Promise of GET /v1/models, fetched once
  textures: [],     // listed textures, newest first
  current: null,    // texture on the map
  nextCursor: null,
  names: new Map(), // texture id -> name, for job labels (listed textures and jobs' textures)
};

function say(message, isError = false) {
  $('status').textContent = message;
  $('status').classList.toggle('error', isError);
}

function sayError(error) {
  if (error instanceof api.ApiError && error.status === 401) { askForKey(); return; }
  say(error instanceof api.ApiError ? `Error ${error.status}: ${error.message}` : String(error.message || error), true);
}

// ---- API key (servers with TEXSPACE_API_KEYS_ENABLED) ----------------------------------
// The first /v1/textures or /v1/jobs call answers 401 when the server needs a key: then
// the key field appears. Without keys nothing here shows and nothing extra is requested.

/** Show the key field with a message saying why (no key yet, or the key was refused). */
function askForKey() {
  const refused = api.hasApiKey();
  const message = refused
    ? 'The API key was refused (unknown or revoked): enter a valid key in the API key field.'
    : 'This server needs an API key: enter yours in the API key field to use the page.';
  $('api-key-section').hidden = false;
  $('api-key-section').classList.remove('accepted');
  $('api-key-note').textContent = refused ? 'The API key was refused.' : 'This server needs an API key.';
  say(message, true);
}
api.setUnauthorizedHandler(askForKey);

function showKeyField() {
  $('api-key-section').hidden = !api.hasApiKey();
  $('api-key').value = api.getApiKey();
  $('api-key-section').classList.add('accepted');
  $('api-key-note').textContent = 'Requests are sent with this key.';
}
showKeyField();

const tileParams = () => ({
  seed: Number($('seed').value) || 0,
  plane: $('plane').value,
  offset: Number($('offset').value),
});

// ---- map -------------------------------------------------------------------------

const textureMap = new TextureMap($('map'), {
  onZoom: (zoom, native) => { $('zoom-info').textContent = `map zoom ${zoom}, native ${native}`; },
  onTileError: (error) => (error?.status === 401 ? askForKey()
    : say('Some tiles failed to load (the server may be busy); pan or zoom to retry.', true)),
});

/**
 * Show the exemplar at the model's working resolution (uploads are resized so their
 * shorter side is manifest.exemplar_short_side), where 1 px matches the map at native zoom.
 */
async function sizeExemplar(texture) {
  const img = $('exemplar');
  img.style.width = img.style.height = '';
  const { width, height } = texture;
  if (!width || !height) return;
  try {
    state.models ||= api.listModels();
    const model = (await state.models).items.find((m) => m.version === texture.model_version);
    const shortSide = model?.manifest?.exemplar_short_side;
    if (!shortSide || state.current !== texture) return;
    const scale = shortSide / Math.min(width, height);
    img.style.width = `${Math.round(width * scale)}px`;
    img.style.height = `${Math.round(height * scale)}px`;
  } catch { /* natural size is the fallback */ }
}

// ---- refinement: an upload's fit job (TEXSPACE_AUTO_FIT) -----------------------------
// A new upload is served from its encoder code at once; a fit job then refines the same
// texture, which serves an interim (the fit's best state seconds in) and its own fitted
// sampler once the job succeeds: the page shows the job's progress, looks for the interim
// now and then, and reloads the map's tiles under new URLs each time (api.tileVersion).

const INTERIM_LOOK_MS = 5000; // how often a refining texture is fetched again for its interim
let stopRefinement = () => {};

function showRefinement(text = '', jobState = '') {
  $('refinement').textContent = text;
  $('refinement').hidden = !text;
  $('refinement').dataset.state = jobState;
}

/** "~40 s", "~3 min": an estimate in seconds, said roughly. */
function roughly(seconds) {
  return seconds < 90 ? `~${Math.max(1, Math.round(seconds))} s` : `~${Math.round(seconds / 60)} min`;
}

/**
 * The status line of a refinement under way, from its job's last state (`job`: state,
 * progress, stage) and the texture's `refinement` (its place in the fit lane, estimates).
 * Queued is never shown as 0%: it says how many fits go first and when refined tiles come.
 */
function refinementText(job, texture) {
  const r = texture?.refinement || {};
  const final = r.final_eta_seconds != null ? `, final in ${roughly(r.final_eta_seconds)}` : '';
  if (job.state === 'queued' && (job.stage === 'interim' || r.stage === 'paused')) {
    const ahead = r.queue_position ? `; goes on after ${r.queue_position} other fit${r.queue_position > 1 ? 's' : ''}` : '; goes on next';
    const served = texture?.sampler === 'interim' ? 'tiles from its first seconds' : "the encoder's tiles still best";
    return `refining, paused: ${served}${ahead}${final}`;
  }
  if (job.state === 'queued') {
    const ahead = r.queue_position ? `${r.queue_position} ahead` : 'next';
    const first = r.interim_eta_seconds != null ? `, refined tiles in ${roughly(r.interim_eta_seconds)}` : '';
    return `queued for refinement (${ahead})${first}${final}`;
  }
  const served = texture?.sampler === 'interim' ? ': tiles from its first seconds' : '';
  return `refining… ${Math.round(fraction(job.progress) * 100)}%${served}${final}`;
}

/** Follow the refinement of `texture` (the one on the map) while it is under way. */
function followRefinement(texture) {
  stopRefinement();
  stopRefinement = () => {};
  const refinement = texture.refinement;
  if (texture.sampler === 'fitted') {
    showRefinement(`tiles from the fitted sampler${structureNote(texture)}`, 'succeeded');
    return;
  }
  if (!refinement || TERMINAL.has(refinement.state)) {
    showRefinement();
    return;
  }
  if (refinement.stage === 'deferred') { // no job yet: look again until the reaper queues it
    showRefinement("refinement deferred: the fit queue is full; it is queued as room frees (the encoder's tiles until then)", 'queued');
    const timer = setInterval(() => {
      if (state.current?.id !== texture.id) return;
      reloadServed(texture.id).then((now) => {
        if (now && now.refinement?.stage !== 'deferred') followRefinement(now);
      }).catch(sayError);
    }, INTERIM_LOOK_MS);
    stopRefinement = () => clearInterval(timer);
    return;
  }
  let last = { state: refinement.state, progress: refinement.progress,
               stage: refinement.stage === 'paused' ? 'interim' : null };
  const say = () => showRefinement(refinementText(last, state.current), last.state);
  say();
  // the texture again now and then: its interim, its place in the lane, fresher estimates
  const timer = setInterval(() => {
    if (state.current?.id !== texture.id || TERMINAL.has(last.state)) return;
    reloadServed(texture.id).then((now) => { if (now && !TERMINAL.has(last.state)) say(); }).catch(sayError);
  }, INTERIM_LOOK_MS);
  const stopFollowing = follow({ id: refinement.job_id, state: refinement.state }, (job) => {
    if (state.current?.id !== texture.id) return;
    last = job;
    if (job.state === 'succeeded') refined(texture.id);
    else if (TERMINAL.has(job.state)) {
      const served = state.current.sampler === 'interim' ? "its fit's first seconds" : "the encoder's code";
      showRefinement(`refinement ${job.state}: tiles from ${served}`, job.state);
    } else say();
  });
  stopRefinement = () => { clearInterval(timer); stopFollowing(); };
}

/**
 * Fetch the texture again; if it is the one on the map, keep it and, where it serves
 * something new (an interim, its fitted sampler), show the new tiles. Its new state, or
 * null when another texture is on the map by now.
 */
async function reloadServed(textureId) {
  const texture = await api.getTexture(textureId);
  state.textures = state.textures.map((t) => (t.id === texture.id ? texture : t));
  if (state.current?.id !== texture.id) return null;
  const changed = texture.sampler !== state.current.sampler;
  state.current = texture;
  if (changed) {
    renderLibrary(); // its new code
    textureMap.update({ v: api.tileVersion(texture) });
  }
  return texture;
}

/** What the fit built in (texture.structure), for the status line: '' when nothing. */
function structureNote(texture) {
  const structure = texture.structure;
  if (!structure) return '';
  // the detail stage's finer octaves (a photo of 512 px and up): drawn above the native zoom
  const detail = structure.detail_zoom ? `; the photo's own detail up to zoom ${structure.detail_zoom}` : '';
  return builtIn(structure) + detail;
}

/** The structure a fit built in, in words: '' when none. */
function builtIn(structure) {
  const turned = structure.straightened ? `, straightened by ${Math.abs(structure.straightened).toFixed(1)}°` : '';
  if (structure.lattice && structure.grain) return ` (boards, grain along ${structure.grain}${turned})`;
  if (structure.lattice) return ' (follows the photo\'s repeat lattice)';
  if (structure.grain) return ` (grain along ${structure.grain}${turned})`;
  const lean = structure.lean ? `leaning ${structure.lean[0].toFixed(0)}° like the photo` : '';
  if (structure.muted_octaves) return ` (even: its coarsest noise octaves muted${lean ? `, ${lean}` : ''})`;
  if (lean) return ` (${lean})`;
  return '';
}

/** The refinement succeeded: the texture's tiles now come from its fitted sampler. */
async function refined(textureId) {
  try {
    const texture = await reloadServed(textureId);
    if (texture) showRefinement(`refined: tiles from the fitted sampler${structureNote(texture)}`, 'succeeded');
  } catch (error) {
    sayError(error);
  }
}

function rememberView() {
  if (state.current && textureMap.textureId) writeView({ t: state.current.id, ...tileParams(), ...textureMap.view() });
}
textureMap.map.on('moveend', rememberView);

async function showTexture(texture, view = null) {
  state.current = texture;
  $('current-name').textContent = texture.name || texture.id;
  const hasExemplar = texture.source !== 'interpolate';
  $('exemplar').parentElement.hidden = !hasExemplar;
  $('no-exemplar').hidden = hasExemplar;
  if (hasExemplar) {
    api.setImageSource($('exemplar'), api.exemplarUrl(texture.id));
    sizeExemplar(texture);
  }
  for (const button of document.querySelectorAll('#texture-list button.pick')) {
    button.setAttribute('aria-pressed', String(button.dataset.id === texture.id));
  }
  followRefinement(texture);
  $('fit-start').disabled = fitRunning || texture.source === 'interpolate'; // a blend has no photo to fit
  try {
    await textureMap.show(texture.id, { ...tileParams(), v: api.tileVersion(texture) }, view);
    document.body.dataset.texture = texture.id;
    rememberView();
    refreshGpuView();
  } catch (error) {
    sayError(error);
  }
}

for (const id of ['seed', 'plane']) {
  $(id).addEventListener('change', () => { textureMap.update(tileParams()); interpolation.refresh(); rememberView(); });
}
$('offset').addEventListener('input', () => { $('offset-value').value = Number($('offset').value).toFixed(2); });
$('offset').addEventListener('change', () => { textureMap.update(tileParams()); rememberView(); });
$('seed-next').addEventListener('click', () => {
  $('seed').value = (Number($('seed').value) || 0) + 1;
  $('seed').dispatchEvent(new Event('change'));
});
$('exemplar').addEventListener('error', () => {
  // A texture without a photo of its own (e.g. a blend from an older server).
  $('exemplar').parentElement.hidden = true;
  $('no-exemplar').hidden = false;
});
$('native-zoom').addEventListener('click', () => textureMap.goNative());

// ---- library and upload ------------------------------------------------------------

/** The listed textures; blends (made by the slider and the strip) only on request. */
function visibleTextures() {
  return $('show-blends').checked ? state.textures : state.textures.filter((t) => t.source !== 'interpolate');
}

function renderLibrary() {
  const textures = visibleTextures();
  for (const t of state.textures) state.names.set(t.id, textureName(t));
  const query = $('texture-search').value;
  const shown = textures.filter((t) => matches(t, query));
  $('texture-list').replaceChildren(...shown.map((t) => textureItem(t, {
    pressed: state.current?.id === t.id, onSelect: showTexture, onDelete: removeTexture,
  })));
  $('no-match').hidden = shown.length > 0 || !textures.length;
  $('load-more').hidden = !state.nextCursor;
  interpolation.setTextures(textures);
  interpolation.refresh();
}

/** Delete a texture (and, on the server, its jobs and files) after asking. */
async function removeTexture(texture) {
  const name = textureName(texture);
  if (!window.confirm(`Delete ${name}, its jobs and their files?`)) return;
  try {
    await api.deleteTexture(texture.id);
  } catch (error) {
    if (!(error instanceof api.ApiError && error.status === 404)) { sayError(error); return; }
  }
  state.textures = state.textures.filter((t) => t.id !== texture.id);
  jobs.forgetTexture(texture.id);
  say(`Deleted ${name}.`);
  if (state.current?.id === texture.id) {
    state.current = null;
    stopRefinement();
    showRefinement();
    textureMap.clear();
    delete document.body.dataset.texture;
    $('current-name').textContent = '(pick a texture)';
    $('exemplar').removeAttribute('src');
    const next = visibleTextures()[0];
    renderLibrary();
    if (next) await showTexture(next);
    return;
  }
  renderLibrary();
}

async function loadTextures(more = false) {
  try {
    const page = await api.listTextures(more ? state.nextCursor : undefined);
    state.textures = more ? state.textures.concat(page.items) : page.items;
    state.nextCursor = page.next_cursor;
    renderLibrary();
  } catch (error) {
    sayError(error);
  }
}
$('load-more').addEventListener('click', () => loadTextures(true));
$('show-blends').addEventListener('change', renderLibrary);
$('texture-search').addEventListener('input', renderLibrary);

/** One line of the upload queue: the file's name and its state (waiting, encoding, done, failed). */
function queueItem(file) {
  const item = document.createElement('li');
  item.innerHTML = '<span class="file"></span> <span class="state"></span>';
  item.querySelector('.file').textContent = file.name;
  item.querySelector('.file').title = file.name;
  const set = (stateName, text) => {
    item.dataset.state = stateName;
    item.querySelector('.state').textContent = text;
  };
  set('waiting', 'waiting');
  return { item, set };
}

/**
 * Upload photos one after another (each is encoded before the next starts, so the server's
 * encoder is not asked for several at once), a line per file in the upload queue; the
 * library lists each as it is done, and the last one uploaded is shown. The name field
 * names a single photo; with several, each is named after its file.
 */
async function uploadAll(files) {
  const typed = $('upload-name').value.trim();
  const lighting = $('upload-even-lighting').checked ? 'even' : 'as-is';
  const widthM = Number($('upload-width-m').value) || null; // (the same width for every photo of a batch)
  const queue = files.map((file) => ({ file, ...queueItem(file) }));
  $('upload-queue').replaceChildren(...queue.map((q) => q.item));
  $('upload-queue').hidden = false;
  let last = null;
  let failed = 0;
  for (const [index, { file, set }] of queue.entries()) {
    if (!file.type.startsWith('image/')) {
      failed += 1;
      set('failed', 'not an image');
      continue;
    }
    const name = (files.length === 1 && typed) || file.name.replace(/\.[^.]+$/, '');
    set('encoding', 'encoding...');
    say(files.length > 1 ? `Encoding ${index + 1} of ${files.length}: ${file.name}...` : `Encoding ${file.name}...`);
    try {
      const texture = await api.uploadTexture(file, name, lighting, widthM);
      state.textures = [texture, ...state.textures.filter((t) => t.id !== texture.id)];
      renderLibrary();
      set('done', 'uploaded');
      last = texture;
    } catch (error) {
      failed += 1;
      set('failed', error instanceof api.ApiError ? `error ${error.status}: ${error.message}` : String(error.message || error));
      if (error instanceof api.ApiError && error.status === 401) { askForKey(); break; }
    }
  }
  if (last) $('upload-name').value = '';
  const done = queue.filter((q) => q.item.dataset.state === 'done').length;
  if (files.length === 1 && last) say(`Uploaded ${last.name || last.id}.`);
  else if (files.length === 1) say(`${files[0].name}: ${queue[0].item.querySelector('.state').textContent}`, true);
  else say(`Uploaded ${done} of ${files.length}${failed ? `; ${failed} failed` : ''}.`, failed > 0);
  if (last) await showTexture(last);
}

wireDropZone($('drop-zone'), $('upload-file'), uploadAll);

// ---- interpolation -------------------------------------------------------------------

const interpolation = new InterpolationPanel({
  selectA: $('interp-a'),
  selectB: $('interp-b'),
  slider: $('interp-t'),
  output: $('interp-t-value'),
  showButton: $('interp-show'),
  strip: $('strip'),
  getParams: tileParams,
  onBlend: (texture) => {
    say(`Showing blend ${texture.name || texture.id}.`);
    showTexture(texture);
  },
  onError: sayError,
});

// ---- 3D: bakes and volumes -------------------------------------------------------------

const jobs = new JobList($('jobs'), { nameOf: (id) => state.names.get(id) });
let viewer = null;

async function getViewer() {
  // three.js is loaded on first use so that the map works even if WebGL is unavailable.
  if (!viewer) {
    const { MeshViewer } = await import('./view3d.js');
    viewer = new MeshViewer($('viewer'));
  }
  return viewer;
}

async function viewResult(url) {
  try {
    await (await getViewer()).load(url);
    say('Bake loaded in the 3D view.');
  } catch (error) {
    sayError(error);
  }
}

/** Recent jobs (any texture), oldest first so the newest ends on top, labelled by texture. */
async function loadRecentJobs() {
  try {
    const page = await api.listJobs(8);
    const unknown = new Set(page.items.map((j) => j.texture_id).filter((id) => id && !state.names.has(id)));
    await Promise.all([...unknown].map((id) => api.getTexture(id)
      .then((t) => state.names.set(id, textureName(t))).catch(() => {})));
    for (const job of page.items.reverse()) jobs.track(job, { onView: viewResult });
  } catch (error) {
    sayError(error);
  }
}

function requireTexture() {
  if (!state.current) { say('Pick or upload a texture first.', true); return false; }
  return true;
}

$('bake-form').addEventListener('submit', async (event) => {
  event.preventDefault();
  if (!requireTexture()) return;
  const mesh = $('bake-mesh').files[0] || sphereObjFile();
  const format = $('bake-format').value;
  const params = {
    resolution: Number($('bake-resolution').value),
    seed: tileParams().seed,
    // Empty = the server's default (the mesh spans 512 exemplar pixels).
    scale: Number($('bake-scale').value) || undefined,
    unitM: Number($('bake-unit').value) || undefined, // at real size: the server needs the photo's width
    format,
    projection: $('bake-projection').value,
  };
  try {
    const job = await api.startBake(state.current.id, mesh, params);
    say(`Bake job ${job.id} started.`);
    jobs.track(job, { onView: viewResult, onSuccess: (_, url) => { if (format === 'glb') viewResult(url); } });
  } catch (error) {
    sayError(error);
  }
});

$('volume-form').addEventListener('submit', async (event) => {
  event.preventDefault();
  if (!requireTexture()) return;
  const resolution = Number($('volume-resolution').value);
  const params = { resolution, seed: tileParams().seed, format: $('volume-format').value };
  try {
    const job = await api.startVolume(state.current.id, params);
    say(`Volume job ${job.id} started.`);
    jobs.track(job, { onSuccess: () => say('Volume ready to download.') });
  } catch (error) {
    sayError(error);
  }
});

// A square image at native zoom (one pixel per exemplar pixel); tileable: it repeats seamlessly.
$('region-form').addEventListener('submit', async (event) => {
  event.preventDefault();
  if (!requireTexture()) return;
  const size = Number($('region-size').value);
  const tileable = $('region-tileable').checked;
  const [format, blocks] = $('region-format').value.split(':'); // "dds:bc7": a DDS of BC7 blocks
  const params = {
    z: 6, x0: 0, y0: 0, width: size, height: size, seed: tileParams().seed, format, tileable,
    ...(blocks ? { dds_compression: blocks } : {}),
  };
  try {
    const job = await api.startRegion(state.current.id, params);
    say(`${tileable ? 'Tileable image' : 'Image'} job ${job.id} started.`);
    jobs.track(job, { onSuccess: () => say('Image ready to download.') });
  } catch (error) {
    sayError(error);
  }
});

// ---- fit: refine a texture (a fit job makes a new texture with its own sampler) -----------

let fitRunning = false;

function showFit(text, progress = null) {
  $('fit-state').textContent = text;
  $('fit-progress').hidden = progress === null;
  if (progress !== null) $('fit-progress').value = progress;
}

$('fit-start').addEventListener('click', async () => {
  if (!requireTexture()) return;
  const source = state.current;
  const name = textureName(source);
  const seconds = Number($('fit-seconds').value) || undefined; // none: the server's default
  fitRunning = true;
  $('fit-start').disabled = true;
  showFit(`fit of ${name}: queued`, 0);
  const ended = () => { fitRunning = false; $('fit-start').disabled = state.current?.source === 'interpolate'; };
  try {
    const job = await api.startFit(source.id, { seconds });
    say(`Fit job ${job.id} started for ${name}.`);
    jobs.track(job, {
      onState: (update) => {
        const status = update.state || 'running';
        if (status === 'succeeded') return; // onSuccess
        if (TERMINAL.has(status)) {
          ended();
          const error = update.error?.detail;
          showFit(`fit of ${name} ${status}${error ? `: ${error}` : ''}`);
        } else {
          showFit(`fit of ${name}: ${status} ${Math.round(fraction(update.progress) * 100)}%`, fraction(update.progress));
        }
      },
      onSuccess: async (done) => {
        ended();
        try {
          const fitted = await api.getTexture(done.output_texture_id);
          state.textures = [fitted, ...state.textures.filter((t) => t.id !== fitted.id)];
          renderLibrary();
          showFit(`fitted: ${textureName(fitted)}`, 1);
          await showTexture(fitted);
        } catch (error) {
          sayError(error);
        }
      },
    });
  } catch (error) {
    ended();
    showFit('');
    sayError(error);
  }
});

// ---- start -----------------------------------------------------------------------------

// A server that evaluates per-point codes can draw the a -> b strip as one image.
api.apiPaths()
  .then((paths) => { interpolation.stripPath = paths.find((p) => p.includes('strip') && !p.includes('{')) || null; })
  .catch(() => {});
getViewer().catch((error) => say(`3D view unavailable: ${error.message}`, true));
/** Open the view in the URL hash (texture, seed, slice, centre, zoom), if any. */
async function openLinkedView() {
  const view = readView([...$('plane').options].map((option) => option.value));
  if (!view) return false;
  if (view.seed !== undefined) $('seed').value = view.seed;
  if (view.plane) $('plane').value = view.plane;
  if (view.offset !== undefined) {
    $('offset').value = view.offset;
    $('offset-value').value = Number($('offset').value).toFixed(2);
  }
  try {
    await showTexture(await api.getTexture(view.t), view);
    return true;
  } catch (error) {
    sayError(error);
    return false;
  }
}

/** Recent jobs, the texture list, then the linked view or the newest texture. */
async function start() {
  await loadTextures(); // first: job labels name their textures
  loadRecentJobs();
  if (!(await openLinkedView()) && visibleTextures().length) await showTexture(visibleTextures()[0]);
}

/** A new (or no) API key: another tenant's textures and jobs, so start over. */
async function restartWithKey(key) {
  api.setApiKey(key);
  jobs.clear();
  stopRefinement();
  showRefinement();
  textureMap.clear();
  Object.assign(state, { textures: [], current: null, nextCursor: null, names: new Map() });
  $('current-name').textContent = '(pick a texture)';
  $('exemplar').removeAttribute('src');
  delete $('exemplar').dataset.src; // drops a fetch still under way for the old key
  delete document.body.dataset.texture;
  renderLibrary();
  say(key ? 'Using the API key.' : 'API key forgotten.');
  showKeyField();
  await start();
}

$('api-key-form').addEventListener('submit', (event) => {
  event.preventDefault();
  const key = $('api-key').value.trim();
  if (!key) { $('api-key').focus(); return; }
  restartWithKey(key);
});
$('api-key-forget').addEventListener('click', () => { $('api-key').value = ''; restartWithKey(''); });

// For the browser tests and the console.
// ---- live GPU view (gpuview.js): drawn only while its panel is open ------------------
const gpuView = new GpuView($('gpu-view'), $('gpu-status'));
function refreshGpuView() {
  if (!$('gpu-panel').open || !state.current) return;
  gpuView.show(state.current.id, tileParams()).catch(sayError);
}
$('gpu-panel').addEventListener('toggle', refreshGpuView);
for (const id of ['seed', 'plane', 'offset']) $(id).addEventListener('change', refreshGpuView);

// ---- the server's limits (GET /v1/limits): the page copies none of its numbers -------------

/** The fit budget, the planes, the formats and the sizes offered, as the server allows them. */
function applyLimits(limits) {
  $('fit-seconds').max = limits.max_fit_seconds;
  $('fit-seconds').value = limits.fit_seconds;
  $('plane').replaceChildren(...limits.planes.map((plane) => new Option(plane, plane)));
  const formats = (id, names, labels = {}) =>
    $(id).replaceChildren(...names.map((f) => new Option(labels[f] ?? f, f)));
  formats('bake-format', limits.formats.bake);
  formats('volume-format', limits.formats.volume);
  // (a square image here). DDS twice: BC1 in the legacy header every reader opens, BC7 (about
  // half BC1's error) in the DX10 header that newer tools read (docs/API.md)
  const regionFormats = limits.formats.region.filter((f) => f !== 'pyramid')
    .flatMap((f) => (f === 'dds' ? ['dds', 'dds:bc7'] : [f]));
  formats('region-format', regionFormats, { dds: 'dds (BC1)', 'dds:bc7': 'dds (BC7)' });
  const offer = (id, allowed) => {
    for (const option of [...$(id).options]) if (!allowed(Number(option.value))) option.remove();
  };
  offer('bake-resolution', (side) => side <= limits.max_bake_resolution);
  offer('volume-resolution', (side) => side <= limits.max_volume_resolution);
  offer('region-size', (side) => side * side <= limits.max_region_pixels);
}

window.texspace = { state, textureMap, gpuView, get viewer() { return viewer; } };
try {
  applyLimits(await api.getLimits());
} catch (error) {
  sayError(error);
}
await start();

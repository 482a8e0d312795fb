"""The fit lane's order: every waiting upload reaches its interim before any fit goes on past
its own (a refinement pauses after its interim, its state stored, and a continuation resumes
it); among tenants, the one whose fits ran least recently goes first; the texture says where
its refinement stands (position, estimates).

The fit is the stand-in of tests/service/helpers.py (no torch), which pauses as model.fit does when
asked to after its interim; the queue keeps its messages (MemoryHuey) until a test runs them.
"""
from __future__ import annotations

import pytest

from service import jobs, keys
from service.db import session_scope
from service.tables import Job, utcnow
from tests.service.helpers import FAKE_INTERIM_CODE, add_fit, drain_fit_lane, run_fit_lane, upload_photo

# every fit publishes its interim before it pauses or goes on
pytestmark = pytest.mark.usefixtures("fits_publish_interims")


def test_waiting_uploads_reach_their_interims_before_any_fit_goes_on(refining, photo, fit_calls) -> None:
    client, services = refining
    textures = [upload_photo(client, photo, name=f"t{k}") for k in range(3)]
    drain_fit_lane(services)
    assert len(fit_calls) == 5  # t0 and t1 pause for the uploads behind them; t2 has no one behind it
    first_stages = [call["interim"] is not None for call in fit_calls]
    assert first_stages == [True, True, True, False, False]
    assert [call["pause"] is not None for call in fit_calls] == first_stages  # a continuation never pauses
    # an upload's detail stage runs only where no other fit waits when its fit ends: the last one
    assert [call.get("detail_wanted") for call in fit_calls] == [None, None, False, False, True]
    for texture in textures:
        now = client.get(f"/v1/textures/{texture['id']}").json()
        assert now["sampler"] == "fitted" and now["refinement"]["stage"] == "done"
        job = client.get(f"/v1/jobs/{texture['refinement']['job_id']}").json()
        assert job["state"] == "succeeded" and job["attempt"] == 1  # a pause spends no attempt
        assert not services.storage.exists(keys.paused_fit_key(job["id"]))  # the paused state is gone
    # each job counts the stages it held the lane for and their seconds (the estimates' measure)
    with session_scope(services.sessions) as session:
        details = [session.get(Job, t["refinement"]["job_id"]).result_details for t in textures]
    assert [d["stages"] for d in details] == [2, 2, 1]
    assert all(d["lane_seconds"] > 0 for d in details)


def test_estimates_take_the_stage_overhead_recent_fits_measured(refining) -> None:
    _, services = refining
    assert jobs.stage_overhead(services) == jobs.FIT_STAGE_OVERHEAD_SECONDS  # no fit finished yet
    # 90-s fits that held the lane 130 s over 2 stages (20 s each) and 105 s in one (15 s)
    finished = {"state": "succeeded", "finished_at": utcnow()}
    add_fit(services, "a", 3, result_details={"lane_seconds": 130.0, "stages": 2}, **finished)
    add_fit(services, "a", 2, result_details={"lane_seconds": 105.0, "stages": 1}, **finished)
    add_fit(services, "a", 1, result_details={"lane_seconds": 130.0, "stages": 2}, **finished)
    add_fit(services, "a", 1, result_details=None, **finished)  # before lane times were kept
    assert jobs.stage_overhead(services) == pytest.approx(20.0)
    queued = add_fit(services, "b", 0)
    with session_scope(services.sessions) as session:
        job = session.get(Job, queued)
    wait = jobs.refinement_wait(services, job)
    interim = services.settings.fit_interim_seconds
    assert wait["position"] == 0 and wait["interim_eta_seconds"] == pytest.approx(interim + 20.0)
    assert wait["final_eta_seconds"] == pytest.approx(90.0 + 20.0)


def test_estimates_follow_the_lane_four_uploads_at_once(refining) -> None:
    """Four uploads, the first fitting: each first stage pauses at its interim for the ones
    behind it but the last, which goes on to its end; then the paused ones continue, oldest
    first. (Before, the estimates had the running fit end first and the last upload's last: on
    an AVX-512 EPYC the floor tiles' final came at 183 s, estimated 80 s, the grass's at 122 s,
    estimated 319 s: ``make bench-refine``.)"""
    _, services = refining
    interim, overhead, budget = services.settings.fit_interim_seconds, jobs.FIT_STAGE_OVERHEAD_SECONDS, 90.0
    running = add_fit(services, None, 4, state="running", progress=0.0)
    queued = [add_fit(services, None, 3 - k) for k in range(3)]
    lane = jobs.fit_lane(services)
    waits = {}
    with session_scope(services.sessions) as session:
        for job_id in [running, *queued]:
            waits[job_id] = jobs.refinement_wait(services, session.get(Job, job_id), lane)
    first = interim + overhead
    assert [waits[j]["interim_eta_seconds"] for j in [running, *queued]] == pytest.approx(
        [first, 2 * first, 3 * first, 4 * first])
    assert [waits[j]["position"] for j in [running, *queued]] == [0, 0, 1, 2]
    last_final = 4 * first + budget - interim
    continuation = budget - interim + overhead
    assert waits[queued[-1]]["final_eta_seconds"] == pytest.approx(last_final)
    assert [waits[j]["final_eta_seconds"] for j in [running, *queued[:2]]] == pytest.approx(
        [last_final + continuation, last_final + 2 * continuation, last_final + 3 * continuation])


def test_a_paused_refinement_serves_its_interim_and_says_so(refining, photo, fit_calls) -> None:
    client, services = refining
    first, second = upload_photo(client, photo), upload_photo(client, photo)
    queued = client.get(f"/v1/textures/{second['id']}").json()["refinement"]
    assert queued["stage"] == "queued" and queued["queue_position"] == 1
    assert 0 < client.get(f"/v1/textures/{first['id']}").json()["refinement"]["interim_eta_seconds"] \
        < queued["interim_eta_seconds"] < queued["final_eta_seconds"]
    run_fit_lane(services)  # the first upload's first stage: interim, then a pause for the second
    paused = client.get(f"/v1/textures/{first['id']}").json()
    assert paused["sampler"] == "interim" and paused["code"] == FAKE_INTERIM_CODE
    assert paused["refinement"]["stage"] == "paused" and paused["refinement"]["state"] == "queued"
    assert paused["refinement"]["interim_eta_seconds"] is None and paused["refinement"]["queue_position"] == 1
    assert services.storage.exists(keys.paused_fit_key(first["refinement"]["job_id"]))
    second_now = client.get(f"/v1/textures/{second['id']}").json()["refinement"]
    assert second_now["queue_position"] == 0  # the second upload's first stage goes before the continuation


def test_one_tenants_burst_delays_another_tenants_first_refinement_by_one_fit(refining) -> None:
    _, services = refining
    burst = [add_fit(services, "a", 10 - k) for k in range(4)]
    other = add_fit(services, "b", 5)
    later = add_fit(services, "c", 1)
    order = [job.id for job in jobs.fit_order(services)]
    assert order == [burst[0], other, later, burst[1], burst[2], burst[3]]
    assert jobs.pick_fit(services, later) == burst[0]  # a message is a turn, not an address


def test_first_stages_go_before_continuations_and_tenants_that_just_ran_wait(refining) -> None:
    _, services = refining
    paused = add_fit(services, "a", 10, stage="interim", progress=0.2)
    whole = add_fit(services, "a", 9)
    with session_scope(services.sessions) as session:  # a POST .../fit job: a new texture, no interim
        session.get(Job, whole).params = {"in_place": False, "seconds": 90.0}
    recent = add_fit(services, "a", 8)
    fresh = add_fit(services, "b", 1)
    ran = add_fit(services, "b", 30)
    with session_scope(services.sessions) as session:  # tenant b's fit ran a moment ago
        job = session.get(Job, ran)
        job.state, job.heartbeat_at = "succeeded", utcnow()
    order = [job.id for job in jobs.fit_order(services)]
    assert order == [recent, fresh, paused, whole]
    assert jobs.fits_waiting_for_interim(services, paused)
    with session_scope(services.sessions) as session:  # only continuations and whole fits left
        for job_id in (recent, fresh):
            session.get(Job, job_id).state = "succeeded"
    assert not jobs.fits_waiting_for_interim(services, paused)


def run_main_lane(services) -> None:
    task = services.huey.dequeue()
    assert task is not None, "no message on the main lane"
    services.huey.execute(task)


def test_jobs_say_which_sampler_they_use_and_wait_for_the_refinement_when_asked(refining, photo) -> None:
    client, services = refining
    texture = upload_photo(client, photo)
    url = f"/v1/textures/{texture['id']}/volumes"
    now = client.post(url, json={"resolution": 4, "format": "npy"}).json()
    later = client.post(url, json={"resolution": 4, "format": "npy", "after_refinement": True}).json()
    assert now["sampler"]["kind"] == "encoder" and now["sampler"]["refining"]
    assert not now["sampler"]["waiting_for_refinement"] and later["sampler"]["waiting_for_refinement"]
    run_main_lane(services)
    run_main_lane(services)
    done = client.get(f"/v1/jobs/{now['id']}").json()
    held = client.get(f"/v1/jobs/{later['id']}").json()
    assert done["state"] == "succeeded" and done["sampler"]["kind"] == "encoder"
    assert held["state"] == "queued" and held["attempt"] == 0  # held back, no attempt spent, not sent again
    assert services.huey.pending_count() == 0
    run_fit_lane(services)  # the refinement ends: the held job is sent again
    assert services.huey.pending_count() == 1
    run_main_lane(services)
    held = client.get(f"/v1/jobs/{later['id']}").json()
    assert held["state"] == "succeeded" and held["attempt"] == 1
    assert held["sampler"]["kind"] == "fitted" and not held["sampler"]["refining"]
    assert held["sampler"]["version"].startswith(texture["model_version"] + "+fit.")


def test_a_turn_whose_fit_another_worker_took_goes_to_the_next(refining) -> None:
    _, services = refining
    first, second = add_fit(services, None, 3), add_fit(services, None, 2)
    assert jobs.claim(services, first) is not None  # another worker's claim, a moment earlier
    claim = jobs.claim_fit_turn(services, first)    # this worker's message named the first
    assert claim is not None and claim.job.id == second
    assert jobs.claim_fit_turn(services, first) is None  # nothing queued: the turn is spent

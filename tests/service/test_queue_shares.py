"""Back-pressure by lane and by tenant: fits have a queue limit of their own, each tenant
fills at most a share of each queue, and an upload whose refinement finds the fit queue
full says so and is refined later (the reaper queues it, oldest upload first) instead of
being silently left unrefined."""
from __future__ import annotations

import pytest

from service import jobs, limits
from service.auth import owner_var
from service.errors import Problem
from tests.service.helpers import add_fit, drain_fit_lane, upload_photo

# every fit publishes its interim before it pauses or goes on, as in test_fit_lane.py
pytestmark = pytest.mark.usefixtures("fits_publish_interims")


def as_tenant(owner: str | None):  # noqa: ANN201
    class Scope:
        def __enter__(self):  # noqa: ANN204
            self.token = owner_var.set(owner)

        def __exit__(self, *exc):  # noqa: ANN002, ANN204
            owner_var.reset(self.token)
    return Scope()


def test_an_upload_whose_fit_queue_is_full_is_deferred_then_refined(refining, photo, fit_calls) -> None:
    client, services = refining
    services.settings.max_queued_fits, services.settings.tenant_queue_share = 2, 1.0
    services.settings.max_queued_jobs = 1  # fits do not count against the other jobs' queue
    first, second, third = (upload_photo(client, photo) for _ in range(3))
    assert [t["refinement"]["stage"] for t in (first, second)] == ["queued", "queued"]
    deferred = third["refinement"]
    assert deferred["stage"] == "deferred" and deferred["state"] == "queued" and deferred["job_id"]
    assert client.get(f"/v1/jobs/{deferred['job_id']}").status_code == 404  # no job until there is room
    volume = client.post(f"/v1/textures/{first['id']}/volumes", json={"resolution": 4})
    assert volume.status_code == 202, volume.text  # another lane, another limit
    assert jobs.served_sampler(services, third["id"])["refining"]  # a job may wait for it (after_refinement)

    assert jobs.reap(services)["refinements"] == 0  # still full: stays deferred
    drain_fit_lane(services)
    assert jobs.reap(services)["refinements"] == 1
    now = client.get(f"/v1/textures/{third['id']}").json()
    assert now["refinement"]["stage"] == "queued" and now["refinement"]["job_id"] == deferred["job_id"]
    assert jobs.reap(services)["refinements"] == 0  # queued once: its deferral is cleared (SQL NULL, not JSON null)
    assert client.get(f"/v1/textures/{third['id']}").json()["refinement"]["job_id"] == deferred["job_id"]
    drain_fit_lane(services)
    assert [client.get(f"/v1/textures/{t['id']}").json()["sampler"] for t in (first, second, third)] == ["fitted"] * 3


def test_a_deferred_upload_is_refined_before_a_newer_one_of_its_tenant(refining, photo, fit_calls) -> None:
    client, services = refining
    services.settings.max_queued_fits, services.settings.tenant_queue_share = 1, 1.0
    first, older, newer = upload_photo(client, photo), upload_photo(client, photo), None
    assert older["refinement"]["stage"] == "deferred"
    drain_fit_lane(services)  # room now, but the reaper has not passed yet
    newer = upload_photo(client, photo)
    assert newer["refinement"]["stage"] == "deferred"  # first come, first refined
    assert jobs.reap(services)["refinements"] == 1
    stages = {t["id"]: t["refinement"]["stage"] for t in client.get("/v1/textures").json()["items"]}
    assert stages[older["id"]] == "queued" and stages[newer["id"]] == "deferred"
    assert stages[first["id"]] == "done"


def test_one_tenant_fills_at_most_its_share_of_each_queue(refining) -> None:
    _, services = refining
    services.settings.max_queued_fits, services.settings.tenant_queue_share = 4, 0.5
    services.settings.api_keys_enabled = True  # (without keys every caller is one tenant)
    for k in range(2):
        add_fit(services, "a", 10 - k)
    with as_tenant("a"), pytest.raises(Problem) as refused:
        limits.check_queue_room(services, "fit")
    assert refused.value.status == 429 and refused.value.slug == "queue-share-used"
    assert refused.value.headers["Retry-After"] == str(services.settings.queue_full_retry_after_seconds)
    assert "2 fits queued" in refused.value.detail and "2 of 4" in refused.value.detail
    with as_tenant("b"):
        limits.check_queue_room(services, "fit")  # another tenant still has room
        limits.check_queue_room(services, "volume")  # and the volume lane is not touched by fits
    for k in range(2):
        add_fit(services, "b", 5 - k)
    with as_tenant("c"), pytest.raises(Problem) as full:
        limits.check_queue_room(services, "fit")
    assert full.value.status == 503 and full.value.slug == "queue-full" and "4 fits" in full.value.detail


def test_a_deferred_refinement_that_cannot_be_queued_for_another_reason_is_dropped(refining, photo,
                                                                                  monkeypatch) -> None:
    """An error other than a full queue (here the database's) leaves the upload unrefined, and
    not deferred: the reaper would otherwise try it again on every pass."""
    client, services = refining
    services.settings.max_queued_fits, services.settings.tenant_queue_share = 1, 1.0
    upload_photo(client, photo)
    deferred = upload_photo(client, photo)
    assert deferred["refinement"]["stage"] == "deferred"
    drain_fit_lane(services)
    tries = []
    monkeypatch.setattr(jobs, "submit", lambda *a, **k: tries.append(1) or (_ for _ in ()).throw(RuntimeError("db")))
    assert jobs.reap(services)["refinements"] == 0 and tries == [1]
    assert client.get(f"/v1/textures/{deferred['id']}").json()["refinement"] is None
    assert jobs.reap(services)["refinements"] == 0 and tries == [1]  # not tried again

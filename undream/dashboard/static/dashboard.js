// undream dashboard: refresh pages about active runs in place, and show a job's details on hover.
// No framework and nothing fetched from elsewhere: this file is all the page runs.
"use strict";

function showCell(event) {
  const cell = event.target.closest("table.grid td[title]");
  const info = document.getElementById("cell-info");
  if (cell && info) {
    info.textContent = cell.getAttribute("title");
  }
}

async function refreshLive() {
  const response = await fetch(window.location.href, { headers: { "X-Requested-With": "refresh" } });
  if (!response.ok) {
    document.getElementById("refresh-note").textContent = "refresh failed: " + response.status;
    return false;
  }
  const page = new DOMParser().parseFromString(await response.text(), "text/html");
  for (const part of document.querySelectorAll("[data-live]")) {
    const fresh = page.getElementById(part.id);
    if (fresh) {
      part.replaceWith(fresh);
    }
  }
  document.getElementById("refresh-note").textContent = page.getElementById("refresh-note").textContent;
  return page.body.hasAttribute("data-refresh");
}

function scheduleRefresh() {
  const seconds = Number(document.body.dataset.refresh || 0);
  if (seconds > 0) {
    window.setTimeout(async () => {
      let again = true;
      try {
        again = await refreshLive();
      } catch (err) {
        document.getElementById("refresh-note").textContent = "refresh failed: " + err;
      }
      if (again) {
        scheduleRefresh();
      } else {
        delete document.body.dataset.refresh;
      }
    }, seconds * 1000);
  }
}

document.addEventListener("DOMContentLoaded", () => {
  document.addEventListener("mouseover", showCell);
  scheduleRefresh();
});

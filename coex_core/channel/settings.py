"""Queue status and operator settings (export and import) of a channel manager.

A part of :class:`~coex_core.channel.manager.ChannelManager` (the API is the manager's)."""

from __future__ import annotations

from typing import Any

from ..errors import ConfigError
from .commands import CommandsMixin
from .links import _PendingSchedule
from .queue import StreamConfig
from .schedule import Schedule

__all__ = ["SettingsMixin"]


class SettingsMixin(CommandsMixin):
    # ========================================================================== settings
    def export_settings(self) -> dict[str, Any]:
        """Operator settings that must survive a restart (JSON-able): stream settings, link
        enable/mute, active and pending schedules."""
        return {
            "version": 1,
            "streams": {str(sid): s.queue.config.to_dict() for sid, s in sorted(self._streams.items())},
            "links": {
                str(link): {
                    "enabled": st.enabled,
                    "muted": st.muted,
                    "spare": st.spare,
                    "schedule": st.current.to_dict(),
                    "pending": None if st.pending is None else {
                        "schedule": st.pending.schedule.to_dict(), "command_id": st.pending.command_id,
                        # a network of several nodes: an update awaiting its commit, or committed
                        **({"fleet": True, "committed": st.pending.committed} if st.pending.fleet else {})},
                }
                for link, st in sorted(self._links.items())
            },
            "command_id": self._command_id,
            "auth": {
                # a restart resumes above the last counter it may have used (see import_settings)
                "sent": self.signer.counter if self.signer is not None else None,
                "accepted": self.verifier.counter if self.verifier is not None else None,
                # a network of several nodes: the counters of each peer's own key
                **({"peers": {str(p): {"sent": self.peer_signers[p].counter,
                                       "accepted": self.peer_verifiers[p].counter}
                              for p in sorted(self.peer_signers)}} if self.peer_signers else {}),
            },
        }

    def import_settings(self, settings: dict[str, Any], now: float | None = None) -> None:
        """Restore :meth:`export_settings` output (unknown streams/links are ignored)."""
        try:
            for sid, d in settings.get("streams", {}).items():
                s = self._streams.get(int(sid))
                if s is not None:
                    s.queue.config = StreamConfig.from_dict(d)
            for lid, d in settings.get("links", {}).items():
                st = self._links.get(int(lid))
                if st is None:
                    continue
                st.enabled = bool(d.get("enabled", st.enabled))
                st.muted = bool(d.get("muted", st.muted))
                st.spare = float(d.get("spare", st.spare))
                if d.get("schedule"):
                    st.current = Schedule.from_dict(d["schedule"])
                    st.switched_at = now
                p = d.get("pending")
                st.pending = None if not p else _PendingSchedule(
                    Schedule.from_dict(p["schedule"]), int(p["command_id"]),
                    fleet=bool(p.get("fleet", False)), committed=bool(p.get("committed", False)))
            self._command_id = int(settings.get("command_id", self._command_id))
            auth = settings.get("auth") or {}
            if self.signer is not None and auth.get("sent") is not None:
                # frames signed after the last save may have left: skip a margin of counters
                self.signer.counter = max(self.signer.counter,
                                          int(auth["sent"]) + self.COUNTER_MARGIN)
            if self.verifier is not None and auth.get("accepted") is not None:
                self.verifier.counter = max(self.verifier.counter, int(auth["accepted"]))
            for p, c in (auth.get("peers") or {}).items():
                if int(p) in self.peer_signers:
                    signer, verifier = self.peer_signers[int(p)], self.peer_verifiers[int(p)]
                    signer.counter = max(signer.counter, int(c["sent"]) + self.COUNTER_MARGIN)
                    verifier.counter = max(verifier.counter, int(c["accepted"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"invalid channel settings: {exc}") from exc

//! The task that drives the broker connection: connects and reconnects with a backoff,
//! subscribes to the archive's acknowledgement, sends the status and the lab tests' records
//! on every connection, and matches the broker's acknowledgements to what was sent.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{Event, EventLoop, Outgoing, Packet, QoS};

use super::state::{Sent, Shared};
use tagdeflect_core::backoff::Backoff;

/// Drives the connection: never cancelled mid-poll, so no packet is half written.
pub(super) async fn drive(shared: Arc<Shared>, mut eventloop: EventLoop, done: Arc<AtomicBool>) {
    let mut backoff = Backoff::new(Duration::from_millis(200), Duration::from_secs(2));
    let mut connections = 0u64;
    let mut last_error: Option<String> = None;
    while !done.load(Ordering::Relaxed) {
        match eventloop.poll().await {
            Ok(Event::Incoming(Packet::ConnAck(_))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                st.connected = true;
                shared.stats.connected.store(1, Ordering::Relaxed);
                if connections > 0 {
                    shared.stats.reconnects.fetch_add(1, Ordering::Relaxed);
                }
                connections += 1;
                backoff.reset();
                last_error = None;
                tracing::info!(to_send = st.todo.len(), unconfirmed = st.unconfirmed(), "MQTT: connected to the broker");
                // The archive's acknowledgement (retained: the current one arrives at once).
                if let Err(e) = shared.client.try_subscribe(shared.ack_topic.clone(), QoS::AtLeastOnce) {
                    tracing::warn!("MQTT: cannot subscribe to {}: {e}", shared.ack_topic);
                }
                shared.send_status(&mut st);
                // The lab tests' records again: a broker restarted without persistence forgot them.
                for i in 0..st.lab.len() {
                    shared.send_lab(&mut st, i);
                }
                shared.pump(&mut st);
            }
            Ok(Event::Incoming(Packet::Publish(p))) => {
                if p.topic == shared.ack_topic {
                    let mut st = shared.state.lock().expect("mqtt state");
                    shared.archive_acked(&mut st, &p.payload);
                }
            }
            Ok(Event::Outgoing(Outgoing::Publish(pkid))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                let who = match st.collided {
                    Some((p, w)) if p == pkid => {
                        st.collided = None;
                        Some(w)
                    }
                    _ => st.order.pop_front(),
                };
                if let Some(who) = who {
                    let qos0 = match who {
                        Sent::Line(_) => shared.qos == QoS::AtMostOnce,
                        Sent::Status | Sent::Lab(_) => false,
                    };
                    if qos0 || pkid == 0 {
                        shared.acked(&mut st, who);
                        shared.pump(&mut st);
                    } else {
                        st.pkids.insert(pkid, who);
                    }
                }
            }
            Ok(Event::Outgoing(Outgoing::AwaitAck(pkid))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                if let Some(w) = st.order.pop_front() {
                    st.collided = Some((pkid, w));
                }
            }
            // QoS 1 (and the status) end with PUBACK, QoS 2 with PUBCOMP.
            Ok(Event::Incoming(Packet::PubAck(rumqttc::PubAck { pkid, .. })))
            | Ok(Event::Incoming(Packet::PubComp(rumqttc::PubComp { pkid, .. }))) => {
                let mut st = shared.state.lock().expect("mqtt state");
                if let Some(w) = st.pkids.remove(&pkid) {
                    shared.acked(&mut st, w);
                }
                shared.pump(&mut st);
            }
            Ok(_) => {}
            Err(e) => {
                {
                    let mut guard = shared.state.lock().expect("mqtt state");
                    let st = &mut *guard;
                    // Everything the client still holds is forgotten (clean session); the
                    // lines in flight go back to be sent.
                    eventloop.clean();
                    eventloop.pending.clear();
                    eventloop.state.events.clear();
                    st.connected = false;
                    shared.stats.connected.store(0, Ordering::Relaxed);
                    let flying: Vec<Sent> =
                        st.order.drain(..).chain(st.pkids.drain().map(|(_, w)| w)).chain(st.collided.take().map(|c| c.1)).collect();
                    for w in flying {
                        if let Sent::Line(seq) = w {
                            st.todo.insert(seq);
                        }
                    }
                    shared.update_stats(st);
                }
                let msg = e.to_string();
                if last_error.as_deref() != Some(msg.as_str()) {
                    tracing::warn!("MQTT: broker unreachable ({msg}); keeping up to {} feed lines in memory, retrying", shared.cap);
                    last_error = Some(msg);
                }
                tokio::time::sleep(backoff.next_delay()).await;
            }
        }
    }
}
